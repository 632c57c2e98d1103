from ..core.cli import run_cli
from .evaluate import main

raise SystemExit(run_cli(main))
