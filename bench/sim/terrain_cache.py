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

The same store keeps the onboard map products of ``nav_map = "on"``
(:func:`cached_arrays`, used by :mod:`bench.maps`) in a folder of their own,
``$LANDBENCH_CACHE_DIR/map``, under the same rules.
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


def cache_dir(kind: str = "terrain") -> Path | None:
    """The cache folder of ``kind`` ("terrain" or "map"), or None when the disk cache is off."""
    root = os.environ.get(CACHE_ENV, "")
    if root.strip().lower() in ("off", "0", "none", "false"):
        return None
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "landbench"
    return base / kind


def source_digest(path: str | Path) -> str:
    """sha256 of a source file's bytes (a generator's code belongs in its products' keys)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _generator_digest() -> str:
    global _source_digest
    if _source_digest is None:
        _source_digest = source_digest(terrain_module.__file__)
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
    return content_address(doc)


def content_address(doc: dict) -> str:
    """sha256 hex of a key document (plain JSON values, serialised with sorted keys): a cache entry's name."""
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


def load_entry(path: Path, key: str) -> tuple[dict, dict[str, np.ndarray]] | None:
    """The header and arrays of the entry ``path``, or None when it is missing or not valid (then it is removed).

    Valid: it reads, its header names ``key`` and this format, and every array matches its sha256.
    """
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
        _remove(path)
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used
    return header, arrays


def store_entry(path: Path, key: str, arrays: dict[str, np.ndarray], meta: dict | None = None) -> None:
    """Write an entry atomically (temporary file in the same folder, then ``os.replace``).

    ``meta``: plain JSON values kept in the header beside the key and the arrays' checksums.
    """
    header = {**(meta or {}), "format": FORMAT_VERSION, "key": key,
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
        _remove(tmp)
        raise


def _remove(path: Path | str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


def _decode_terrain(header: dict, arrays: dict[str, np.ndarray]) -> Terrain:
    patch = None
    if "patch_height_m" in arrays:
        patch = TerrainPatch(height_m=arrays["patch_height_m"], size_m=float(header["patch_size_m"]),
                             albedo=arrays["patch_albedo"])
    return Terrain(height_m=arrays["height_m"], size_m=float(header["size_m"]), albedo=arrays["albedo"],
                   craters=arrays["craters"], boulders=arrays["boulders"], patch=patch,
                   relief_shaded=bool(header.get("relief_shaded", False)))


def _encode_terrain(terrain: Terrain) -> tuple[dict[str, np.ndarray], dict]:
    return _arrays(terrain), {"size_m": terrain.size_m,
                              "patch_size_m": terrain.patch.size_m if terrain.patch is not None else None,
                              "relief_shaded": terrain.relief_shaded}


def _load_decoded(path: Path, key: str, decode):
    """The product in the entry ``path`` (``decode(header, arrays)``), or None when the entry is missing,
    not valid, or one ``decode`` cannot use (raising KeyError, ValueError or TypeError); a bad entry is removed."""
    entry = load_entry(path, key)
    if entry is None:
        return None
    try:
        return decode(*entry)
    except (KeyError, ValueError, TypeError):
        _remove(path)
        return None


def load(path: Path, key: str) -> Terrain | None:
    """The terrain in the entry ``path``, or None when it is missing or not valid (then it is removed)."""
    return _load_decoded(path, key, _decode_terrain)


def store(path: Path, key: str, terrain: Terrain) -> None:
    """Write the terrain's entry atomically (:func:`store_entry`)."""
    store_entry(path, key, *_encode_terrain(terrain))


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


def cached_arrays(kind: str, key: str, generate, decode, encode):
    """A product from the disk cache of ``kind``, else ``generate()`` stored there (when the cache is on).

    Args:
        kind: The cache folder's name ("terrain", "map").
        key: The product's content address (a sha256 hex of everything that shapes it).
        generate: Makes the product.
        decode: ``(header, arrays) -> product``; raises KeyError, ValueError or TypeError for an entry it
            cannot use (which is then removed and the product generated).
        encode: ``product -> (arrays, meta)`` for :func:`store_entry`.
    """
    folder = cache_dir(kind)
    if folder is None:
        return generate()
    path = folder / f"{key}.npz"
    product = _load_decoded(path, key, decode)
    if product is not None:
        return product
    product = generate()
    try:
        store_entry(path, key, *encode(product))
        _prune(folder, keep=path)
    except OSError:
        pass  # a read-only or full disk costs the cache, never the run
    return product


def cached_terrain(cfg: TerrainConfig, terrain_seed: int, sun_elevation_deg: float, sun_azimuth_deg: float,
                   generate) -> Terrain:
    """The terrain from the disk cache, else ``generate()`` stored there (when the cache is on)."""
    if cfg.kind != "procedural":
        return generate()
    key = terrain_key(cfg, terrain_seed, sun_elevation_deg, sun_azimuth_deg)
    return cached_arrays("terrain", key, generate, _decode_terrain, _encode_terrain)
