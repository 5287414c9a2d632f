"""On-disk cache of generated terrains, content-addressed and safe under concurrent workers.

A procedural terrain is a pure function of its configuration, its seed, the
sun direction it is baked for, the generator's code and the numerical
libraries. Sweeps and regressions reuse terrain seeds (common random numbers),
and the default tile takes seconds to generate, so each generated terrain is
kept on disk under a key that hashes all of these:

* ``TerrainConfig`` (every field, as JSON), the resolved terrain seed, the sun
  elevation and azimuth;
* the bytes of ``models/terrain.py`` (any change to the generator is a new key);
* :data:`FORMAT_VERSION`, the numpy and scipy versions.

An entry is one ``<key>.npz`` (uncompressed) holding the arrays and a JSON
header with the key and the sha256 of every array. It is written to a
temporary file in the same folder and renamed into place (``os.replace``), so
a reader never sees a half-written entry and two workers writing the same key
both leave a complete one. An entry that cannot be read, whose key differs, or
whose checksums do not match (truncated, bit rot, edited) is never trusted:
it is removed and the terrain generated anew.

The folder is ``$LANDBENCH_CACHE_DIR/terrain`` (default
``~/.cache/landbench/terrain``); ``LANDBENCH_CACHE_DIR=off`` turns the disk
cache off. Terrains loaded from a DEM file are not cached. When the folder
grows past ``LANDBENCH_TERRAIN_CACHE_MB`` (default 2048 MB), the least
recently used entries are removed.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

import models.terrain as terrain_module
from models.terrain import Terrain, TerrainConfig, TerrainPatch

FORMAT_VERSION = 1
CACHE_ENV = "LANDBENCH_CACHE_DIR"
MAX_MB_ENV = "LANDBENCH_TERRAIN_CACHE_MB"
DEFAULT_MAX_MB = 2048
_ARRAYS = ("height_m", "albedo", "craters", "boulders", "patch_height_m", "patch_albedo")

_source_digest: str | None = None


def cache_dir() -> Path | None:
    """The terrain cache folder, or None when the disk cache is off."""
    root = os.environ.get(CACHE_ENV, "")
    if root.strip().lower() in ("off", "0", "none", "false"):
        return None
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "landbench"
    return base / "terrain"


def _generator_digest() -> str:
    global _source_digest
    if _source_digest is None:
        _source_digest = hashlib.sha256(Path(terrain_module.__file__).read_bytes()).hexdigest()
    return _source_digest


def terrain_key(cfg: TerrainConfig, terrain_seed: int, sun_elevation_deg: float, sun_azimuth_deg: float) -> str:
    """The content address (sha256 hex) of a procedural terrain."""
    import scipy

    doc = {
        "format": FORMAT_VERSION,
        "config": json.loads(cfg.model_dump_json()),
        "terrain_seed": int(terrain_seed),
        "sun_elevation_deg": float(sun_elevation_deg).hex(),
        "sun_azimuth_deg": float(sun_azimuth_deg).hex(),
        "generator_sha256": _generator_digest(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _sha256(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).data).hexdigest()


def _arrays(terrain: Terrain) -> dict[str, np.ndarray]:
    out = {"height_m": terrain.height_m, "albedo": terrain.albedo, "craters": terrain.craters,
           "boulders": terrain.boulders}
    if terrain.patch is not None:
        out["patch_height_m"] = terrain.patch.height_m
        out["patch_albedo"] = terrain.patch.albedo
    return out


def load(path: Path, key: str) -> Terrain | None:
    """The terrain in the entry ``path``, or None when it is missing or not valid (then it is removed)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(bytes(z["header"]).decode("utf-8"))
            if header.get("key") != key or header.get("format") != FORMAT_VERSION:
                raise ValueError("key mismatch")
            arrays = {}
            for name, digest in header["sha256"].items():
                a = z[name]
                if _sha256(a) != digest:
                    raise ValueError(f"checksum mismatch in {name}")
                arrays[name] = a
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, json.JSONDecodeError):
        with contextlib.suppress(OSError):
            path.unlink()
        return None
    try:
        patch = None
        if "patch_height_m" in arrays:
            patch = TerrainPatch(height_m=arrays["patch_height_m"], size_m=float(header["patch_size_m"]),
                                 albedo=arrays["patch_albedo"])
        terrain = Terrain(height_m=arrays["height_m"], size_m=float(header["size_m"]), albedo=arrays["albedo"],
                          craters=arrays["craters"], boulders=arrays["boulders"], patch=patch)
    except (KeyError, ValueError, TypeError):
        with contextlib.suppress(OSError):
            path.unlink()
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used
    return terrain


def store(path: Path, key: str, terrain: Terrain) -> None:
    """Write the entry atomically (temporary file in the same folder, then ``os.replace``)."""
    arrays = _arrays(terrain)
    header = {"format": FORMAT_VERSION, "key": key, "size_m": terrain.size_m,
              "patch_size_m": terrain.patch.size_m if terrain.patch is not None else None,
              "sha256": {name: _sha256(a) for name, a in arrays.items()}}
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem[:16]}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, header=np.frombuffer(json.dumps(header).encode("utf-8"), np.uint8), **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _prune(folder: Path, keep: Path) -> None:
    """Remove the least recently used entries while the folder is over its size limit."""
    try:
        max_bytes = float(os.environ.get(MAX_MB_ENV, DEFAULT_MAX_MB)) * 2**20
    except ValueError:
        max_bytes = DEFAULT_MAX_MB * 2**20
    entries = []
    for p in folder.glob("*.npz"):
        with contextlib.suppress(OSError):
            st = p.stat()
            entries.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in entries)
    for _, size, p in sorted(entries):
        if total <= max_bytes:
            break
        if p == keep:
            continue
        with contextlib.suppress(OSError):
            p.unlink()
            total -= size


def cached_terrain(cfg: TerrainConfig, terrain_seed: int, sun_elevation_deg: float, sun_azimuth_deg: float,
                   generate) -> Terrain:
    """The terrain from the disk cache, else ``generate()`` stored there (when the cache is on)."""
    folder = cache_dir()
    if folder is None or cfg.kind != "procedural":
        return generate()
    key = terrain_key(cfg, terrain_seed, sun_elevation_deg, sun_azimuth_deg)
    path = folder / f"{key}.npz"
    terrain = load(path, key)
    if terrain is not None:
        return terrain
    terrain = generate()
    try:
        store(path, key, terrain)
        _prune(folder, keep=path)
    except OSError:
        pass  # a read-only or full disk costs the cache, never the run
    return terrain
