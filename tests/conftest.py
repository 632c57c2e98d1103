from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data`` beside the checkout; skips when a clone does not have it."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"reference data folder {SHARED_DATA} is absent (only the project's own machines have it)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """A 5-scene, 3-slice, 40x32 synthetic dataset made by the real CLI (7-blade aperture, cat-eye)."""
    from data_tools.synth import main

    out = tmp_path_factory.mktemp("data") / "tiny"
    rc = main(["--out", str(out), "--scenes", "5", "--size", "40", "32", "--slices", "3",
               "--aperture", "polygon:7", "--cat-eye", "0.5", "--seed", "7"])
    assert rc == 0
    return out
