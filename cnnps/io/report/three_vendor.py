"""three.js, vendored: the pinned release's files, checked, for the report page.

``vendor/three/`` (package data next to this module) holds files of the npm package
``three`` at the version pinned in its ``three.json``, byte for byte as in the package's
tarball: ``build/three.core.js`` and ``build/three.module.js`` (the library: the npm
package ships no minified build) and ``examples/jsm/controls/OrbitControls.js``, with
three.js's MIT ``LICENSE``. ``three.json`` records the version, the tarball's npm
``dist.integrity`` (sha512) and each file's sha256.

:func:`three_sources` reads the files for a page and checks each against its sha256
first (an InputError naming the file when one differs). :func:`vendor_three` (the
command ``python -m cnnps.io.report.three_vendor VERSION``) refreshes the folder from the
registry: ``npm pack three@VERSION`` fetches the tarball, whose sha512 must equal the
registry's ``dist.integrity`` (``npm view``); then the files are extracted and
``three.json`` rewritten. Nothing is ever fetched when a page is written.
"""

from __future__ import annotations

import base64
import functools
import hashlib
import json
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from cnnps.infra.errors import ConfigError, InputError

VENDOR_DIR = Path(__file__).resolve().parent / "vendor" / "three"
MANIFEST = "three.json"
# the file kept in VENDOR_DIR -> its path in the npm tarball
FILES = {
    "three.core.js": "package/build/three.core.js",
    "three.module.js": "package/build/three.module.js",
    "OrbitControls.js": "package/examples/jsm/controls/OrbitControls.js",
    "LICENSE": "package/LICENSE",
}


def manifest(folder: Path = VENDOR_DIR) -> dict:
    """``three.json``: ``version``, ``integrity`` (npm's sha512 of the tarball),
    ``tarball`` (its name), ``files`` (name -> {``from``, ``sha256``, ``bytes``})."""
    return json.loads((folder / MANIFEST).read_text(encoding="utf-8"))


@functools.lru_cache(maxsize=2)
def three_sources(folder: Path = VENDOR_DIR) -> dict:
    """The vendored files' text by name, each checked against its sha256 in three.json,
    with ``version``. Cached per process."""
    info = manifest(folder)
    out = {"version": info["version"]}
    for name, entry in info["files"].items():
        data = (folder / name).read_bytes()
        if hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise InputError(folder / name, f"differs from three.js {info['version']} as vendored "
                                            f"(sha256 in {MANIFEST}); run python -m cnnps.io.report.three_vendor "
                                            f"{info['version']}")
        out[name] = data.decode("utf-8")
    return out


def sri_sha512(data: bytes) -> str:
    """npm's ``dist.integrity`` form of ``data``'s digest: ``sha512-<base64>``."""
    return "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode("ascii")


def _npm(*args: str, cwd: Path | None = None) -> str:
    try:
        done = subprocess.run(["npm", *args], cwd=cwd, capture_output=True, text=True, check=False, timeout=300)
    except FileNotFoundError:
        raise ConfigError("npm not found: vendoring three.js needs the npm client") from None
    if done.returncode != 0:
        raise ConfigError(f"npm {' '.join(args)} failed: {done.stderr.strip()[-500:]}")
    return done.stdout


def check_tarball(tarball: Path, integrity: str) -> None:
    """Raise ConfigError unless ``tarball``'s sha512 is ``integrity`` (``sha512-...``)."""
    got = sri_sha512(tarball.read_bytes())
    if got != integrity:
        raise ConfigError(f"{tarball.name}: sha512 {got} is not the registry's dist.integrity {integrity}")


def unpack(tarball: Path, integrity: str, folder: Path) -> dict:
    """Extract :data:`FILES` of a checked ``tarball`` into ``folder``; write and return
    the manifest."""
    check_tarball(tarball, integrity)
    version = tarball.name.removeprefix("three-").removesuffix(".tgz")
    files = {}
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(tarball, "r:gz") as tar:
        for name, member in FILES.items():
            data = tar.extractfile(member).read()
            (folder / name).write_bytes(data)
            files[name] = {"from": member.removeprefix("package/"), "sha256": hashlib.sha256(data).hexdigest(),
                           "bytes": len(data)}
    info = {"package": "three", "version": version, "license": "MIT", "tarball": tarball.name,
            "integrity": integrity, "files": files}
    (folder / MANIFEST).write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")
    return info


def vendor_three(version: str, folder: Path = VENDOR_DIR) -> dict:
    """Fetch three@``version`` with npm, check it against the registry's integrity and
    unpack it into ``folder``; returns the manifest."""
    integrity = json.loads(_npm("view", f"three@{version}", "dist.integrity", "--json"))
    with tempfile.TemporaryDirectory() as tmp:
        packed = json.loads(_npm("pack", f"three@{version}", "--json", "--pack-destination", tmp, cwd=Path(tmp)))
        tarball = Path(tmp) / packed[0]["filename"]
        if packed[0].get("integrity") not in (None, integrity):
            raise ConfigError(f"npm pack reports integrity {packed[0]['integrity']}, the registry {integrity}")
        return unpack(tarball, integrity, folder)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m cnnps.io.report.three_vendor VERSION")
    done = vendor_three(sys.argv[1])
    print(f"three.js {done['version']} ({done['integrity']}) -> {VENDOR_DIR}")
