"""Print the development requirement set declared in pyproject.toml.

Used by the Makefile: one requirement per line (runtime deps, the `test` extra and the build
backend), with ``--no-deps`` the packages installed without their dependencies ([tool.sync4d]
no-deps), and with ``--hash`` a short digest of both sets, which keys the install stamp so that
`make setup` reinstalls only when the requirements themselves change.

Runs on the host interpreter before the virtualenv exists, so it uses the standard library only.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    try:
        import tomli as tomllib  # type: ignore[no-redef]
    except ModuleNotFoundError:
        sys.exit("dev_requirements.py: needs Python >= 3.11 (tomllib) or the tomli package")

PYPROJECT = Path(__file__).resolve().parent.parent / "pyproject.toml"


def requirements() -> list[str]:
    data = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))
    reqs: list[str] = []
    reqs += data["build-system"]["requires"]
    reqs += data["project"].get("dependencies", [])
    reqs += data["project"].get("optional-dependencies", {}).get("test", [])
    seen: set[str] = set()
    out = []
    for r in reqs:
        r = r.strip()
        if r and r not in seen:
            seen.add(r)
            out.append(r)
    return out


def no_deps_requirements() -> list[str]:
    """Packages installed with ``pip install --no-deps`` ([tool.sync4d] no-deps)."""
    data = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))
    return list(data.get("tool", {}).get("sync4d", {}).get("no-deps", []))


def main(argv: list[str]) -> int:
    reqs = requirements()
    no_deps = no_deps_requirements()
    if argv[1:] == ["--hash"]:
        blob = "\n".join(reqs) + "\n--no-deps\n" + "\n".join(no_deps)
        print(hashlib.sha256(blob.encode()).hexdigest()[:16])
    elif argv[1:] == ["--no-deps"]:
        print("\n".join(no_deps))
    elif not argv[1:]:
        print("\n".join(reqs))
    else:
        print("usage: dev_requirements.py [--hash | --no-deps]", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
