"""Turn pip's pylock.toml into provisioning/requirements.lock: every dependency pinned with its
SHA-256 hashes, in the requirements format `pip install --require-hashes` reads.

    python provisioning/lock_requirements.py pylock.toml provisioning/requirements.lock

The lock names no index or file location (those differ between the machine that locks and
the appliance); the hashes alone decide what may be installed. The project itself is left
out: install.sh puts the release's own code on the virtualenv's path.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

HEADER = """\
# The appliance's Python dependencies, pinned with their SHA-256 hashes, for CPython 3.11 on
# x86_64 Linux (Debian 12). provisioning/install.sh installs exactly these into the release's
# virtualenv with `pip install --require-hashes --no-deps`, so a changed or substituted package
# on the index stops the install instead of reaching the appliance. Regenerate after changing
# pyproject.toml's dependencies: `make lock` (pip lock, then provisioning/lock_requirements.py).
"""


def requirements(lock: dict, project: str = "fluorosim") -> str:
    lines = [HEADER]
    for p in sorted(lock["packages"], key=lambda p: p["name"]):
        if p["name"] == project or "version" not in p:
            continue
        files = list(p.get("wheels", [])) + ([p["sdist"]] if "sdist" in p else [])
        hashes = [f["hashes"]["sha256"] for f in files]
        if not hashes:
            raise SystemExit(f"{p['name']}: no sha256 hash in the lock; cannot pin it")
        lines.append(f"{p['name']}=={p['version']} \\")
        lines += [f"    --hash=sha256:{h}" + (" \\" if i < len(hashes) - 1 else "") for i, h in enumerate(hashes)]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    Path(sys.argv[2]).write_text(requirements(tomllib.loads(Path(sys.argv[1]).read_text())))
