"""``python -m sync4d`` entry point."""

from sync4d.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
