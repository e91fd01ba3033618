"""`python -m tests.golden --regenerate`: rewrite the golden CAN log (then review its diff)."""

from __future__ import annotations

import argparse

from tests.golden import DEFAULT_LOG, regenerate


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.golden", description=__doc__)
    parser.add_argument(
        "--regenerate", action="store_true", help=f"rewrite {DEFAULT_LOG.name} from a fresh run"
    )
    args = parser.parse_args()
    if not args.regenerate:
        parser.error("nothing to do: pass --regenerate to rewrite the golden CAN log")
    path = regenerate()
    print(f"wrote {path} ({len(path.read_text().splitlines())} frames); review the diff")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
