"""`python -m tests.golden --regenerate`: rewrite the golden CAN logs (then review their diff)."""

from __future__ import annotations

import argparse

from tests.golden import regenerate


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.golden", description=__doc__)
    parser.add_argument(
        "--regenerate", action="store_true", help="rewrite the golden CAN logs from fresh runs"
    )
    args = parser.parse_args()
    if not args.regenerate:
        parser.error("nothing to do: pass --regenerate to rewrite the golden CAN logs")
    for path in regenerate():
        print(f"wrote {path}; review the diff")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
