#!/usr/bin/env python3
"""Write specs/models/<type>.json: every builtin model at its default parameters, as volpuzzle JSON (mm).

The files let a user open, inspect or edit the paper's shapes with any tool that reads the format, and let
`volpuzzle info` be tried on them. Deterministic: running it twice writes the same bytes.
Usage: python3 scripts/make_models.py [OUTPUT_DIR]   (default: specs/models beside this repository's specs)
"""

import sys
from pathlib import Path

from volpuzzle.io import save_model
from volpuzzle.models import BUILTINS


def main(argv):
    out = Path(argv[1]) if len(argv) > 1 else Path(__file__).resolve().parent.parent / "specs" / "models"
    out.mkdir(parents=True, exist_ok=True)
    for name, (make, defaults) in BUILTINS.items():
        path = out / f"{name}.json"
        save_model(make(**defaults), path, units="mm")
        print(f"{path}: {path.stat().st_size / 1024:.1f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
