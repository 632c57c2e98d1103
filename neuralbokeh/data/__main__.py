from ..core.cli import run_cli
from .check import main

raise SystemExit(run_cli(main))
