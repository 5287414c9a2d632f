"""Recorded descents: fly the closed loop and keep everything the flight software was given.

Inputs: a resolved scenario and a list of seeds (``landbench record``).
Outputs: one folder per seed, ``DS/seed_NNN/``, that an open-loop replay
(:mod:`bench.evaluation.replay`) feeds back to a rebuilt flight software
without MuJoCo or a renderer:

``messages.parquet``
    The order of events, one row per event: ``kind`` (``imu``, ``attitude``,
    ``altimeter``, ``image``, ``control``), ``t_ns`` and ``index`` into that
    kind's arrays. The rows are in the order the flight software received them.
``sensors.npz``
    The messages' contents, float64 as sent: ``imu_t_ns``, ``imu_f_B`` (N, 3),
    ``imu_omega_B`` (N, 3); ``attitude_t_ns``, ``attitude_q_LB`` (N, 4);
    ``altimeter_t_ns``, ``altimeter_range_m``, ``altimeter_valid``,
    ``altimeter_boresight_B`` (N, 3); ``control_t_ns``, ``control_legs``
    (N, 4) bool (the contact message of each control tick).
``frames.npz``
    Every camera frame as sent, lossless: ``t_ns`` (F,), ``frames`` (F, H, W) uint8.
    Stored without compression: a camera's noise leaves deflate only about 18 %
    to gain, and inflating them cost a replay more time than its tracker
    (older recordings with compressed frames read the same way).
``calibration.npz``
    The camera calibration sent with the frames: ``K`` (3, 3), ``R_BC`` (3, 3).
``camera_truth.npz``
    Per frame: ``t_ns``, the truth camera pose ``R_LC`` (F, 3, 3) (OpenCV camera
    frame to L) and ``r_CL_L`` (F, 3) [m]; with ``--depth`` also ``depth``
    (F, H, W) float32 z-depth [m] (what truth correspondences need, see
    :mod:`bench.evaluation.track_eval`).
``truth.parquet``
    The truth at every control tick: ``t_ns``, ``t_s``, position, velocity,
    attitude, rate, mass, propellant and the IMU's true accelerometer bias.
``telemetry.parquet``, ``summary.json``, ``scenario.toml``
    The closed loop's own files (telemetry holds the flight software's
    estimates ``nav_*``).
``manifest.json``
    Format and version, landbench version, git commit, seed, the resolved
    scenario (TOML text), package versions and the sha256 of every file.
    Written last: a folder without it is not a recording.

:func:`open_recording` checks a folder (format, version, checksums) and loads it.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.report.io import atomic_write_bytes, atomic_write_text, json_safe
from bench.scenario import Scenario, ScenarioError, scenario_from_dict, scenario_to_toml

FORMAT = "landbench-recording"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)
MANIFEST = "manifest.json"
MESSAGES = "messages.parquet"
SENSORS = "sensors.npz"
FRAMES = "frames.npz"
CALIBRATION = "calibration.npz"
CAMERA_TRUTH = "camera_truth.npz"
TRUTH = "truth.parquet"
TELEMETRY = "telemetry.parquet"
SUMMARY = "summary.json"
SCENARIO = "scenario.toml"
REQUIRED_FILES = (MESSAGES, SENSORS, FRAMES, CALIBRATION, CAMERA_TRUTH, TRUTH, TELEMETRY, SUMMARY, SCENARIO)
KINDS = ("imu", "attitude", "altimeter", "image", "control")
MAX_SEEDS = 10_000


# --------------------------------------------------------------------------- seeds
def parse_seeds(text: str) -> list[int]:
    """``"1-3"`` -> [1, 2, 3]; ``"1,4,7"`` -> [1, 4, 7]; parts may be mixed (``"1-3,9"``).

    Raises:
        ValueError: One line saying what is wrong (bad syntax, negative, a
            reversed range, a repeated seed, too many seeds).
    """
    hint = "expected a range a-b or a comma list, e.g. --seeds 1-3 or --seeds 1,4,7"
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        lo, sep, hi = part.partition("-")
        try:
            a = int(lo)
            b = int(hi) if sep else a
        except ValueError:
            raise ValueError(f"--seeds {text!r}: {hint}") from None
        if a < 0 or b < 0:
            raise ValueError(f"--seeds {text!r}: seeds are integers >= 0")
        if b < a:
            raise ValueError(f"--seeds {text!r}: range {part!r} runs backwards; write {b}-{a}")
        if b - a + len(seeds) >= MAX_SEEDS:
            raise ValueError(f"--seeds {text!r}: more than {MAX_SEEDS} seeds")
        seeds.extend(range(a, b + 1))
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds {text!r}: a seed is given twice")
    return seeds


def seed_dir_name(seed: int) -> str:
    return f"seed_{seed:03d}"


# --------------------------------------------------------------------------- recording
class DatasetRecorder:
    """The :class:`bench.sim.run.Recorder` of ``landbench record``: keeps copies of everything, in order."""

    def __init__(self, want_depth: bool = False) -> None:
        self.want_depth = want_depth
        self.events: list[tuple[str, int, int]] = []  # (kind, t_ns, index)
        self.imu: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.attitude: list[tuple[int, np.ndarray]] = []
        self.altimeter: list[tuple[int, float, bool, np.ndarray]] = []
        self.frames: list[tuple[int, np.ndarray]] = []
        self.calibration: tuple[np.ndarray, np.ndarray] | None = None
        self.camera: list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self.control: list[tuple[int, np.ndarray]] = []
        self.truth: list[tuple] = []

    def _event(self, kind: str, t_ns: int, store: list) -> None:
        self.events.append((kind, int(t_ns), len(store) - 1))

    def message(self, kind: str, msg: Any) -> None:
        if kind == "imu":
            self.imu.append((msg.t_ns, np.array(msg.f_B, float), np.array(msg.omega_B, float)))
            self._event(kind, msg.t_ns, self.imu)
        elif kind == "attitude":
            self.attitude.append((msg.t_ns, np.array(msg.q_LB, float)))
            self._event(kind, msg.t_ns, self.attitude)
        elif kind == "altimeter":
            self.altimeter.append((msg.t_ns, float(msg.range_m), bool(msg.valid), np.array(msg.boresight_B, float)))
            self._event(kind, msg.t_ns, self.altimeter)
        elif kind == "image":
            image = np.asarray(msg.image)
            if image.dtype != np.uint8 or image.ndim != 2:
                raise ValueError(f"record: camera frames must be (H, W) uint8, got {image.dtype} {image.shape}")
            K, R = np.array(msg.K, float), np.array(msg.R_BC, float)
            if self.calibration is None:
                self.calibration = (K, R)
            elif not (np.array_equal(K, self.calibration[0]) and np.array_equal(R, self.calibration[1])):
                raise ValueError("record: the camera calibration changed during the descent; format 1 holds one")
            self.frames.append((msg.t_ns, image.copy()))
            self._event(kind, msg.t_ns, self.frames)
        else:
            raise ValueError(f"record: unknown message kind {kind!r}")

    def camera_truth(self, t_ns: int, R_LC: np.ndarray, r_CL_L: np.ndarray, depth: np.ndarray | None) -> None:
        self.camera.append((int(t_ns), np.array(R_LC, float), np.array(r_CL_L, float),
                            None if depth is None else np.array(depth, np.float32)))

    def control_tick(self, t_ns: int, contact: Any, truth: Any, accel_bias_B: np.ndarray) -> None:
        self.control.append((int(t_ns), np.array(contact.legs, bool)))
        self._event("control", t_ns, self.control)
        self.truth.append((int(t_ns), *truth.r_BL_L, *truth.v_BL_L, *truth.q_LB, *truth.omega_B,
                           float(truth.mass_kg), float(truth.propellant_kg), *np.asarray(accel_bias_B, float)))

    # ------------------------------------------------------------------ files
    TRUTH_COLUMNS = ("t_ns", "r_x_m", "r_y_m", "r_z_m", "v_x_mps", "v_y_mps", "v_z_mps",
                     "q_w", "q_x", "q_y", "q_z", "omega_x_radps", "omega_y_radps", "omega_z_radps",
                     "mass_kg", "propellant_kg", "accel_bias_x_mps2", "accel_bias_y_mps2", "accel_bias_z_mps2")

    def truth_columns(self) -> dict[str, np.ndarray]:
        cols = {n: np.array(v) for n, v in zip(self.TRUTH_COLUMNS, zip(*self.truth, strict=True), strict=True)}
        cols["t_ns"] = cols["t_ns"].astype(np.int64)
        cols = {"t_s": cols["t_ns"] / 1e9, **cols}
        return cols

    def sensor_arrays(self) -> dict[str, np.ndarray]:
        def stack(rows: list, i: int, shape: tuple, dtype: Any) -> np.ndarray:
            return np.array([r[i] for r in rows], dtype=dtype).reshape((len(rows), *shape))

        return {
            "imu_t_ns": stack(self.imu, 0, (), np.int64),
            "imu_f_B": stack(self.imu, 1, (3,), float),
            "imu_omega_B": stack(self.imu, 2, (3,), float),
            "attitude_t_ns": stack(self.attitude, 0, (), np.int64),
            "attitude_q_LB": stack(self.attitude, 1, (4,), float),
            "altimeter_t_ns": stack(self.altimeter, 0, (), np.int64),
            "altimeter_range_m": stack(self.altimeter, 1, (), float),
            "altimeter_valid": stack(self.altimeter, 2, (), bool),
            "altimeter_boresight_B": stack(self.altimeter, 3, (3,), float),
            "control_t_ns": stack(self.control, 0, (), np.int64),
            "control_legs": stack(self.control, 1, (4,), bool),
        }


def _npz_bytes(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, **arrays)
    return buf.getvalue()


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _git_commit() -> str | None:
    root = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return out + ("-dirty" if dirty else "") if out else None


def _version(*dists: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    for d in dists:
        try:
            return version(d)
        except PackageNotFoundError:
            continue
    return None


def package_versions() -> dict[str, str | None]:
    """Versions of the packages a recording's contents depend on."""
    import cv2

    return {
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "mujoco": _version("mujoco"),
        "opencv": cv2.__version__,
        "filterpy": _version("filterpy"),
        "scipy": _version("scipy"),
        "pyarrow": _version("pyarrow"),
    }


def check_recordable(scenario: Scenario) -> None:
    """Raise a one-line ValueError when the scenario cannot be recorded in format 1."""
    if scenario.vision == "on" and scenario.tracks == "truth":
        raise ValueError("record: tracks = 'truth' feeds truth tracks, not messages, to the flight software; "
                         "format 1 records camera frames: use tracks = 'vision' (or vision = 'off')")
    resets = [k for k, f in enumerate(scenario.faults) if getattr(f, "kind", None) == "computer_reset"]
    if resets:
        raise ValueError(f"record: faults[{resets[0]}] is a computer_reset, which an open-loop replay cannot "
                         "reproduce (it does not restart the flight software from its checkpoint); leave it out of "
                         "[[faults]] when recording")


def with_seed(scenario: Scenario, seed: int) -> Scenario:
    return scenario_from_dict({**scenario.model_dump(mode="json"), "seed": int(seed)})


def record_seed(scenario: Scenario, out: Path, depth: bool = False, progress: bool = False) -> dict[str, Any]:
    """Fly one landing with a recorder and write its recording into ``out`` (replaced whole, or left untouched).

    Returns:
        The manifest written.
    """
    from bench.report.report import write_telemetry_parquet
    from bench.sim.run import run

    check_recordable(scenario)
    rec = DatasetRecorder(want_depth=depth)
    result = run(scenario, progress=progress, recorder=rec)
    if not rec.truth:
        raise RuntimeError(f"record: seed {scenario.seed}: the run had no control tick")

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq

        kinds, times, index = zip(*rec.events, strict=True)
        table = pa.table({"kind": pa.array(kinds, pa.string()), "t_ns": pa.array(times, pa.int64()),
                          "index": pa.array(index, pa.int64())})
        buf = io.BytesIO()
        pq.write_table(table, buf, compression="zstd")
        atomic_write_bytes(tmp / MESSAGES, buf.getvalue())
        atomic_write_bytes(tmp / SENSORS, _npz_bytes(rec.sensor_arrays()))
        cam = scenario.camera
        frames = (np.stack([f for _, f in rec.frames]) if rec.frames
                  else np.zeros((0, cam.height_px, cam.width_px), np.uint8))
        atomic_write_bytes(tmp / FRAMES, _npz_bytes({"t_ns": np.array([t for t, _ in rec.frames], np.int64),
                                                     "frames": frames}, compress=False))
        K, R_BC = rec.calibration if rec.calibration is not None else (np.full((3, 3), np.nan), np.full((3, 3), np.nan))
        atomic_write_bytes(tmp / CALIBRATION, _npz_bytes({"K": K, "R_BC": R_BC}))
        camera = {"t_ns": np.array([c[0] for c in rec.camera], np.int64),
                  "R_LC": np.array([c[1] for c in rec.camera], float).reshape(-1, 3, 3),
                  "r_CL_L": np.array([c[2] for c in rec.camera], float).reshape(-1, 3)}
        if depth and rec.camera:
            camera["depth"] = np.stack([c[3] for c in rec.camera])
        atomic_write_bytes(tmp / CAMERA_TRUTH, _npz_bytes(camera))
        write_telemetry_parquet(rec.truth_columns(), tmp / TRUTH)
        write_telemetry_parquet(result.telemetry, tmp / TELEMETRY)
        atomic_write_text(tmp / SUMMARY, json.dumps(json_safe(result.summary), indent=2) + "\n")
        toml = scenario_to_toml(scenario)
        atomic_write_text(tmp / SCENARIO, toml)
        manifest = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "landbench_version": _version("landbench"),
            "git_commit": _git_commit(),
            "seed": scenario.seed,
            "scenario_toml": toml,
            "packages": package_versions(),
            "platform": json_safe(result.summary.get("platform")),
            "depth": bool(depth),
            "counts": {"events": len(rec.events), "imu": len(rec.imu), "attitude": len(rec.attitude),
                       "altimeter": len(rec.altimeter), "image": len(rec.frames), "control": len(rec.control)},
            "outcome": result.summary["outcome"],
            "files": {name: {"sha256": sha256_file(tmp / name), "bytes": (tmp / name).stat().st_size}
                      for name in REQUIRED_FILES},
        }
        atomic_write_text(tmp / MANIFEST, json.dumps(manifest, indent=2) + "\n")
        tmp.chmod(0o777 & ~_umask())
        _replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


def _umask() -> int:
    import os

    mask = os.umask(0)
    os.umask(mask)
    return mask


def _replace_dir(src: Path, dst: Path) -> None:
    """Move the finished folder into place; an older recording there is removed only after."""
    import os

    old = None
    if dst.exists():
        old = dst.with_name(f".{dst.name}.old.{os.getpid()}")
        os.replace(dst, old)
    os.replace(src, dst)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def record_dataset(scenario: Scenario, seeds: list[int], out: Path, depth: bool = False,
                   progress: bool = False) -> list[tuple[Path, dict[str, Any]]]:
    """Record one descent per seed into ``out/seed_NNN`` (see the module docstring)."""
    check_recordable(scenario)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file; give a folder")
    done = []
    for seed in seeds:
        path = out / seed_dir_name(seed)
        done.append((path, record_seed(with_seed(scenario, seed), path, depth=depth, progress=progress)))
    return done


# --------------------------------------------------------------------------- reading
@dataclass
class Recording:
    """One verified recording, loaded (see the module docstring for the arrays)."""

    path: Path
    manifest: dict[str, Any]
    scenario_toml: str
    events: tuple[np.ndarray, np.ndarray, np.ndarray]  # (kind codes into KINDS, t_ns, index)
    sensors: dict[str, np.ndarray]
    frames_t_ns: np.ndarray
    frames: np.ndarray
    K: np.ndarray
    R_BC: np.ndarray
    camera: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    telemetry: dict[str, np.ndarray]
    summary: dict[str, Any]

    @property
    def seed(self) -> int:
        return int(self.manifest["seed"])


def find_recordings(path: Path) -> list[Path]:
    """The recordings under ``path``: the folder itself if it is one, else its ``seed_*`` sub-folders."""
    if not path.exists():
        raise ValueError(f"dataset {str(path)!r} does not exist")
    if not path.is_dir():
        raise ValueError(f"dataset {str(path)!r} is a file; give the folder written by landbench record")
    if (path / MANIFEST).exists():
        return [path]
    found = sorted(p for p in path.iterdir() if p.is_dir() and (p / MANIFEST).exists())
    bare = sorted(p.name for p in path.iterdir() if p.is_dir() and p.name.startswith("seed_") and p not in found)
    if bare:  # a recording whose manifest is gone would otherwise drop out of the replay unnoticed
        raise ValueError(f"dataset {str(path)!r}: {bare[0]} has no {MANIFEST}; re-record that seed or remove the "
                         "folder")
    if not found:
        raise ValueError(f"dataset {str(path)!r} holds no recording (no {MANIFEST} in it or in a seed_* folder)")
    return found


def verify_recording(path: Path) -> dict[str, Any]:
    """Check a recording's manifest (format, version) and every file's sha256; return the manifest.

    Raises:
        ValueError: One line naming the folder and what is wrong.
    """
    try:
        manifest = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"recording {str(path)!r}: {MANIFEST} cannot be read: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ValueError(f"recording {str(path)!r}: {MANIFEST} is not a {FORMAT} manifest")
    version = manifest.get("format_version")
    if version not in SUPPORTED_VERSIONS:
        raise ValueError(f"recording {str(path)!r}: format version {version!r} is unknown to this landbench "
                         f"(it reads {', '.join(map(str, SUPPORTED_VERSIONS))}); re-record it or update landbench")
    files = manifest.get("files")
    if not isinstance(files, dict) or set(REQUIRED_FILES) - set(files):
        raise ValueError(f"recording {str(path)!r}: {MANIFEST} does not list every file of format {version}")
    for name, entry in files.items():
        f = path / name
        if not f.is_file():
            raise ValueError(f"recording {str(path)!r}: {name} is missing")
        if not isinstance(entry, dict) or sha256_file(f) != entry.get("sha256"):
            raise ValueError(f"recording {str(path)!r}: {name} does not match its sha256 in {MANIFEST} "
                             "(the file was changed or damaged); refusing to replay it")
    seed = manifest.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"recording {str(path)!r}: {MANIFEST} has no seed (a non-negative integer), got {seed!r}")
    if (path / SCENARIO).read_text(encoding="utf-8") != manifest.get("scenario_toml"):
        raise ValueError(f"recording {str(path)!r}: {SCENARIO} differs from the scenario in {MANIFEST}")
    return manifest


def open_recording(path: Path, manifest: dict[str, Any] | None = None) -> Recording:
    """Verify (:func:`verify_recording`) and load one recording.

    ``manifest``: what :func:`verify_recording` returned for this folder just before
    (a replay checks every recording before it starts), so it is not checked twice.
    """
    import pyarrow.parquet as pq

    from bench.report.report import read_telemetry_parquet

    if manifest is None:
        manifest = verify_recording(path)
    table = pq.read_table(path / MESSAGES)
    kinds = table.column("kind").to_pylist()
    code = {k: i for i, k in enumerate(KINDS)}
    if set(kinds) - set(code):
        raise ValueError(f"recording {str(path)!r}: unknown message kinds {sorted(set(kinds) - set(code))}")
    events = (np.array([code[k] for k in kinds], np.int64), table.column("t_ns").to_numpy(),
              table.column("index").to_numpy())
    with np.load(path / SENSORS) as z:
        sensors = {k: z[k] for k in z.files}
    with np.load(path / FRAMES) as z:
        frames_t, frames = z["t_ns"], z["frames"]
    with np.load(path / CALIBRATION) as z:
        K, R_BC = z["K"], z["R_BC"]
    with np.load(path / CAMERA_TRUTH) as z:
        camera = {k: z[k] for k in z.files}
    return Recording(
        path=path, manifest=manifest, scenario_toml=manifest["scenario_toml"], events=events, sensors=sensors,
        frames_t_ns=frames_t, frames=frames, K=K, R_BC=R_BC, camera=camera,
        truth=read_telemetry_parquet(path / TRUTH), telemetry=read_telemetry_parquet(path / TELEMETRY),
        summary=json.loads((path / SUMMARY).read_text(encoding="utf-8")),
    )


def recorded_scenario(toml_text: str, overrides: list[str] | tuple[str, ...] = ()) -> Scenario:
    """The recorded scenario with ``overrides`` applied (validated)."""
    import tomllib

    from bench.scenario import apply_override

    try:
        data = tomllib.loads(toml_text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"recorded scenario is not valid TOML: {exc}") from None
    for assignment in overrides:
        apply_override(data, assignment)
    return scenario_from_dict(data)
