"""The network's configuration: everything needed to rebuild either architecture (torch-free).

A checkpoint stores ``ModelConfig.to_dict()``; :func:`neuralbokeh.networks.build_model` rebuilds
the network from it. The ``[model]`` table of a training config sets the fields that are not
decided by the data (see :data:`FROM_DATA`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from ..core.tiling import TileLayout

ARCHITECTURES = ("lens", "paper")
PUPIL_INITS = ("disk", "gaussian", "aperture")
FILLS = ("background", "normalize")
KERNELS = ("growing", "fixed3")
TILINGS = ("overlap", "none", "no_overlap")
HEADS = ("identity", "paper")


@dataclass(frozen=True)
class ModelConfig:
    """Everything needed to rebuild the network (stored in every checkpoint).

    Args:
        image_height, image_width: the resolution the network is built for (px).
        blocks: number N of residual blocks (from the data's largest CoC, see
            ``optics.blocks_for_coc``), >= 0.
        features: feature channels per tile, >= 1.
        tile: tile core size t (px), >= 1.
        overlap: extra context t_o on every side of a tile (px), 0 <= 2 t_o <= t.
        tiling: ``"overlap"`` (the paper), ``"no_overlap"`` (t_o forced to 0) or ``"none"``
            (one tile covering the image).
        kernels: ``"growing"`` (2n+1, the paper) or ``"fixed3"`` (ablation).
        head: ``"identity"`` or ``"paper"`` (see the module doc).
        fft_min_kernel: kernel size from which per-channel convolutions use the FFT (no grad).
        fft_min_kernel_train: the same when gradients are computed.
        architecture: ``"lens"`` (default: :class:`neuralbokeh.lensnet.LensBokeh`, the skeleton
            with a learned lens) or ``"paper"`` (:class:`NeuralBokeh`, the paper as written).
        coc_scale_px: the CoC input's px per unit (the data's largest |CoC|); the lens
            architecture needs it (> 0) to size its kernels.
        norm_scale, norm_offset: the colour normalisation's ``s`` and ``o`` (linear units), so
            the lens architecture works in linear light.
        pupil_size: samples per side of each learned pupil grid (lens), >= 4.
        pupil_init: the lens architecture's starting pupil: ``"disk"``, ``"gaussian"`` (the
            baseline's profile) or ``"aperture"`` (the shape in ``init_aperture``).
        occlusion_margin_px: CoC difference (px) over which light changes from "same surface"
            to "in front of / behind" the receiving pixel (lens), > 0.
        init_aperture: ``ApertureModel.to_dict()`` of the data (for ``pupil_init = "aperture"``).
        fill: what the lens architecture puts where its coverage falls short (what a blurred
            foreground uncovers): ``"background"`` (the visible background around the occluder,
            as the reference renderer's default) or ``"normalize"`` (divide by the coverage;
            checkpoints written before this option).
        (``features``, ``overlap`` semantics, ``head`` and the FFT thresholds: paper only;
        ``tile``, ``overlap``, ``tiling``, ``kernels``, ``blocks``: both.)
    """

    image_height: int
    image_width: int
    blocks: int
    features: int = 12
    tile: int = 200
    overlap: int = 60
    tiling: str = "overlap"
    kernels: str = "growing"
    head: str = "identity"
    fft_min_kernel: int = 15
    fft_min_kernel_train: int = 5
    architecture: str = "lens"
    coc_scale_px: float = 0.0
    norm_scale: float = 0.18
    norm_offset: float = 0.0018
    pupil_size: int = 48
    pupil_init: str = "disk"
    occlusion_margin_px: float = 2.0
    init_aperture: dict | None = None
    fill: str = "background"

    def __post_init__(self) -> None:
        for name in ("image_height", "image_width", "features", "tile", "fft_min_kernel", "fft_min_kernel_train"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if not isinstance(self.blocks, int) or self.blocks < 0:
            raise ValueError(f"blocks must be an integer >= 0, got {self.blocks!r}")
        if not isinstance(self.overlap, int) or self.overlap < 0 or 2 * self.overlap > self.tile:
            raise ValueError(f"overlap must be an integer with 0 <= 2 * overlap <= tile ({self.tile}), got {self.overlap!r}")
        if not isinstance(self.pupil_size, int) or self.pupil_size < 4:
            raise ValueError(f"pupil_size must be an integer >= 4, got {self.pupil_size!r}")
        for name in ("coc_scale_px", "norm_offset"):
            if not (isinstance(self.__getattribute__(name), (int, float)) and math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {getattr(self, name)!r}")
        for name in ("norm_scale", "occlusion_margin_px"):
            if not (isinstance(getattr(self, name), (int, float)) and math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {getattr(self, name)!r}")
        if self.architecture == "lens" and self.coc_scale_px <= 0:
            raise ValueError(f"architecture 'lens' needs coc_scale_px > 0 px, got {self.coc_scale_px!r}")
        for name, allowed in (("tiling", TILINGS), ("kernels", KERNELS), ("head", HEADS),
                              ("architecture", ARCHITECTURES), ("pupil_init", PUPIL_INITS), ("fill", FILLS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")

    @property
    def layout(self) -> TileLayout:
        """The tile grid actually used (``tiling = "none"``: one tile; ``"no_overlap"``: no context)."""
        return TileLayout.for_image(self.image_height, self.image_width, self.tile, self.overlap, self.tiling)

    @property
    def num_tiles(self) -> int:
        return self.layout.num_tiles

    def kernel_size(self, n: int) -> int:
        """Kernel size of residual block n (1-based)."""
        return 3 if self.kernels == "fixed3" else 2 * n + 1

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown model config keys {sorted(unknown)}; expected {sorted(known)}")
        if "architecture" not in d:  # checkpoints written before the switch hold the paper's network
            d = {**d, "architecture": "paper"}
        if "fill" not in d:  # written before the background fill: they were trained normalising
            d = {**d, "fill": "normalize"}
        return cls(**d)
