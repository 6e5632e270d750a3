"""The ``synth`` command line (renderer commands arrive with the renderer)."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from lensfit import __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="synth", description="Thin-lens renderer whose defocus blur is known exactly.")
    parser.add_argument("--version", action="version", version=f"synth {__version__}")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    build_parser().parse_args(argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
