"""The ``landbench`` command line.

Every sub-command validates all of its input (scenario, overrides, paths)
before it writes anything; a user mistake prints one ``landbench: error:``
line and exits with status 2. A defect found while flying (an error no input
check foresaw) prints its traceback and one ``landbench: internal error:``
line, and exits with status 70 (``EX_SOFTWARE``).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import sys
import traceback
from pathlib import Path
from typing import NoReturn

from bench.errors import SimulationDefectError

EXIT_USAGE = 2
EXIT_INTERNAL = 70  # sysexits.h EX_SOFTWARE: a defect of landbench, not of the input


# The scenario's schema imports the flight software's filter, and with it filterpy and SciPy
# (about 0.9 s): it is imported when a command first needs it, not when the command line is parsed,
# so that a campaign can start its workers' fork server first (see _start_workers_early).
def load_scenario(*args, **kwargs):
    """:func:`bench.scenario.load_scenario`, imported on first use."""
    from bench.scenario import load_scenario as load

    return load(*args, **kwargs)


def scenario_to_toml(scenario) -> str:
    """:func:`bench.scenario.scenario_to_toml`, imported on first use."""
    from bench.scenario import scenario_to_toml as to_toml

    return to_toml(scenario)


def _start_workers_early(args: argparse.Namespace) -> None:
    """A campaign flown on local workers: start their fork server before this process imports the simulation.

    The server's imports and the master's own (scenario schema, campaign,
    report) then run at once on two cores instead of one after the other;
    nothing else about the campaign changes.
    """
    if args.backend == "local" and not getattr(args, "dry_run", False):
        from bench.campaign.workers import start_worker_server

        start_worker_server(args.workers)


def _add_scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", default=None, help="scenario TOML file (default: the bundled default)")
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a scenario field, e.g. --set seed=7 --set sun.elevation_deg=20 (repeatable)",
    )


def _add_preset_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default=None, metavar="NAME",
                   help="lay a named preset over the scenario, under --set: a fault preset (landbench faults list) "
                        "or the hazardous terrain of issue 14 (hazardous)")


def _json(doc: object) -> str:
    """``--json`` output: valid JSON (a NaN or an infinity, say an error median over no tracks, is null)."""
    from bench.report.io import json_safe

    return json.dumps(json_safe(doc), indent=2, allow_nan=False)


def _check_out(path: str, suffixes: tuple[str, ...], flag: str) -> Path:
    out = Path(path)
    if out.suffix.lower() not in suffixes:
        raise ValueError(f"{flag} {path!r}: expected a file ending in {' or '.join(suffixes)}")
    if out.exists() and out.is_dir():
        raise ValueError(f"{flag} {path!r} is a folder; give a file name")
    # Its folder must be one that can be made and written: checked before any work, so that a second output
    # that cannot be written does not leave the first one written (or replaced) by a failed command.
    folder = next(p for p in out.absolute().parents if p.exists())
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{flag} {path!r}: {folder} is not a folder this user can write in; give another path")
    return out


# --------------------------------------------------------------------------- commands
def cmd_scenario_show(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario, args.overrides, args.preset)
    sys.stdout.write(scenario_to_toml(scenario))
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from bench.sim.render import render_view

    out = _check_out(args.out, (".png",), "--out")
    depth_out = _check_out(args.depth, (".npy",), "--depth") if args.depth else None
    if not (math.isfinite(args.altitude) and args.altitude > 0):
        raise ValueError(f"--altitude {args.altitude}: must be a finite height > 0 m above the landing site")
    scenario = load_scenario(args.scenario, args.overrides)
    written = render_view(scenario, args.altitude, out, depth_out, noise=not args.no_noise)
    for p in written:
        print(p)
    return 0


def cmd_world(args: argparse.Namespace) -> int:
    from bench.sim.render import draw_world

    out = _check_out(args.out, (".png",), "--out")
    scenario = load_scenario(args.scenario, args.overrides)
    print(draw_world(scenario, out))
    return 0


def cmd_perf(args: argparse.Namespace) -> int:
    from bench.evaluation.perf import format_perf, run_perf

    scenario = load_scenario(args.scenario, args.overrides)
    if args.campaign is not None:
        from bench.evaluation.perf import format_campaign_perf, run_campaign_perf

        workers = _int_list(args.campaign_workers, "--campaign-workers")
        if len(set(workers)) != len(workers):  # each count flies the cases into its own folder: found after flying
            raise ValueError(f"--campaign-workers {args.campaign_workers}: a worker count is repeated; give each "
                             "once, e.g. 1,2")
        result = run_campaign_perf(scenario, args.campaign, workers, campaign_seed=scenario.seed,
                                   backend=args.backend)
        print(_json(result) if args.json else format_campaign_perf(result))
        return 0 if all(v["identical_to_baseline"] for v in result["results"].values()) else 1
    result = run_perf(scenario, frames=args.frames)
    print(_json(result) if args.json else format_perf(result))
    return 0


def _int_list(text: str, flag: str) -> tuple[int, ...]:
    try:
        return tuple(int(t) for t in text.split(","))
    except ValueError:
        raise ValueError(f"{flag} {text!r}: expected comma-separated integers, e.g. 1,2") from None


def cmd_track_eval(args: argparse.Namespace) -> int:
    from bench.evaluation.track_eval import REPORT_KEYS, format_track_eval, run_track_eval

    frames = args.frames if args.frames is not None else (150 if args.imagery == "descent" else 48)
    if frames < 3:
        raise ValueError(f"--frames {frames}: need at least 3 frames")
    if args.repeats < 1:
        raise ValueError(f"--repeats {args.repeats}: must be >= 1")
    scenario = load_scenario(args.scenario, args.overrides)
    if args.imagery == "textures":
        from bench.evaluation.textures_eval import format_textures_eval, load_texture, run_textures_eval

        load_texture("gravel")  # a clear one-line error before any work when scikit-image is missing
        reports = [run_textures_eval(size, frames, args.repeats, tracker_config=scenario.tracker)
                   for size in (args.size or [256])]
        if args.json:
            print(_json(reports[0] if len(reports) == 1 else reports))
        else:
            print("\n\n".join(format_textures_eval(r, REPORT_KEYS) for r in reports))
        return 0
    report = run_track_eval(scenario, args.size or [256, 512], frames, args.repeats, tracker_config=scenario.tracker)
    print(_json(report) if args.json else format_track_eval(report))
    return 0


def cmd_vision_figures(args: argparse.Namespace) -> int:
    from bench.sim.descent import render_descent
    from bench.evaluation.vision_figures import write_vision_figures

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {args.out!r} is a file; give a folder")
    if args.frames < 3:
        raise ValueError(f"--frames {args.frames}: the figures need 3 consecutive frames; give --frames 3 or more")
    if args.start is not None and not 0 <= args.start <= args.frames - 3:
        raise ValueError(f"--start {args.start}: the figures show frames START..START+2 of the {args.frames} rendered; "
                         f"give --start from 0 to {args.frames - 3} (or more --frames)")
    scenario = load_scenario(args.scenario, args.overrides)
    # The tracker's configuration for this camera (as the tracker scales it), checked before anything is rendered.
    cam = scenario.camera
    cfg = scenario.tracker.for_side(min(cam.width_px, cam.height_px))
    if min(cam.width_px, cam.height_px) < cfg.template_size:
        raise ValueError(f"camera.width_px x camera.height_px = {cam.width_px} x {cam.height_px}: the figures' "
                         f"templates are tracker.template_size = {cfg.template_size} px; give a camera of at least "
                         f"{cfg.template_size} px a side (or a smaller tracker.template_size)")
    descent = render_descent(scenario, args.frames, with_depth=False)
    # Three consecutive frames from the middle of the descent, as in the paper's Fig. 2 (by default frame 20,
    # or the last three of a shorter descent).
    k = min(DEFAULT_FIGURE_START, args.frames - 3) if args.start is None else args.start
    for p in write_vision_figures(list(descent.frames[k:]), out, config=cfg):
        print(p)
    return 0


EXIT_NOT_LANDED = 3
DEFAULT_FIGURE_START = 20  # vision-figures: the first frame shown by default


def _start_helper_server() -> None:
    """A run's second processes (``VideoProcess``, ``PlotProcess``) fork from the workers' server,
    started now so that the server's imports overlap this process's own."""
    from bench.campaign.workers import start_worker_server

    start_worker_server(1)


# The file each command's results are known by: an --out folder holding another command's results is refused,
# so that a run, a campaign or a comparison never writes over (or beside) another's.
RESULT_FILES = (("summary.json", "a run's results"), ("campaign.json", "a campaign"),
                ("faults.json", "a fault matrix"), ("sweep.json", "a sweep"), ("compare.json", "a comparison"),
                ("metrics.json", "a replay"), ("manifest.json", "a recording"))


def _output_folder(value: str, own: str) -> Path:
    """``--out`` as a folder this command may write: not a file, and holding no other command's results
    (``own``: the file of this command's, whose earlier results it may replace)."""
    out = Path(value)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {value!r} is a file; give a folder")
    for name, what in RESULT_FILES:
        if name != own and (out / name).is_file():
            raise ValueError(f"--out {value!r} holds {what} ({name}); give another folder, so that it stays intact")
    return out


def _flags_given(args: argparse.Namespace, *flags: str, defaults: dict[str, object] | None = None) -> list[str]:
    """The scenario arguments (a scenario file, ``--set``, ``--preset``) and the ``flags`` given on this command
    line: set, and not at their default (``defaults``: by attribute, for those whose default is not None)."""
    defaults = defaults or {}
    named = (("a scenario file", "scenario"), ("--set", "overrides"), ("--preset", "preset"),
             *((f, f.lstrip("-").replace("-", "_")) for f in flags))
    return [name for name, attr in named if getattr(args, attr, None) not in (None, [], (), defaults.get(attr))]


def _resume_takes_nothing_else(args: argparse.Namespace, *flags: str, mode: str = "--resume") -> None:
    """``--resume DIR`` (or ``mc --replay DIR``) reads the scenario and the design from DIR: a scenario file,
    ``--set``, ``--preset`` or a design flag given beside it would be ignored, so it is refused."""
    given = _flags_given(args, *flags)
    if given:
        folder = getattr(args, mode.lstrip("-"))
        anew = "start anew with --out" if mode == "--resume" else "run the changed case with landbench run"
        raise ValueError(f"{mode} {folder} takes its scenario and settings from that folder; drop "
                         f"{', '.join(given)} (or {anew})")


def cmd_run(args: argparse.Namespace) -> int:
    _start_helper_server()
    from bench.report.run_outputs import run_and_write

    out = _output_folder(args.out, "summary.json")
    scenario = load_scenario(args.scenario, args.overrides, args.preset)
    summary, table = run_and_write(scenario, out, video=not args.no_video, progress=True, video_process=True,
                                   plot_process=True)
    print(table)
    return 0 if summary["landed"] else EXIT_NOT_LANDED


def cmd_mc(args: argparse.Namespace) -> int:
    if args.replay:
        if args.case is None or not args.out:
            raise ValueError("--replay DIR needs --case I and --out RUN")
        _resume_takes_nothing_else(args, mode="--replay")  # the case flies as the campaign flew it
        return _mc_replay(Path(args.replay), args.case, Path(args.out))
    _start_workers_early(args)
    from bench.campaign import mc

    directory = Path(args.resume or args.out or "")
    if not (args.resume or args.out):
        raise ValueError("give --out DIR for a new campaign, or --resume DIR")
    if args.resume:
        # A resumed campaign is defined by its folder: base scenario, seed and size.
        _resume_takes_nothing_else(args)
        meta_path = directory / mc.CAMPAIGN
        if not meta_path.exists():
            raise ValueError(f"--resume {directory}: no {mc.CAMPAIGN} there; start the campaign with --out")
        meta = mc.read_meta(meta_path, ("campaign_seed", "runs"), "--resume")
        runs = args.runs if args.runs is not None else meta["runs"]
        seed = args.seed if args.seed is not None else meta["campaign_seed"]
        base = load_scenario(directory / mc.BASE_SCENARIO)
    else:
        if args.runs is None:
            raise ValueError("--runs N is required for a new campaign")
        _output_folder(args.out, mc.CAMPAIGN)
        base = load_scenario(args.scenario, args.overrides, args.preset)
        runs, seed = args.runs, (args.seed if args.seed is not None else base.seed)
    args.runs = runs
    rows = mc.run_campaign(base, args.runs, directory, seed, workers=args.workers, resume=bool(args.resume),
                           dry_run=args.dry_run, retention=args.retention, case_timeout_s=args.case_timeout,
                           progress=True, backend=args.backend, address=args.address,
                           cases_per_worker=args.cases_per_worker)
    if args.dry_run:
        print(f"dry run: {args.runs} dispersed scenarios in {directory / mc.CASES}/NNNNN/scenario.toml")
        return 0
    from bench.evaluation.consistency import CONSISTENCY_FILE, consistency_table
    from bench.report.mc_report import campaign_table, write_campaign_report

    crit = base.landing.model_dump()
    terrain = None
    if "terrain.seed" not in base.dispersions:  # one terrain for all cases: draw it under the points
        from bench.sim.world_builder import build_terrain

        terrain = build_terrain(base)
    write_campaign_report(rows, crit, directory / mc.REPORT, terrain=terrain,
                          title=f"{base.name}: {len(rows)} cases, campaign seed {seed}",
                          sun_elevation_deg=base.sun.elevation_deg, sun_azimuth_deg=base.sun.azimuth_deg)
    print(campaign_table(rows, crit))
    print(consistency_table(json.loads((directory / CONSISTENCY_FILE).read_text())))
    print(f"cases: {directory / mc.CASES_PARQUET}, consistency: {directory / CONSISTENCY_FILE}, "
          f"report: {directory / mc.REPORT}")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    _start_workers_early(args)
    from bench.campaign import sweep

    if args.resume:
        _resume_takes_nothing_else(args, "--grid", "--lhs", "--sobol", "--range")
        directory = Path(args.resume)
        doc = sweep.run_sweep({}, directory, [], None, 1, directory, 0, workers=args.workers, resume=True,
                              retention=args.retention, case_timeout_s=args.case_timeout, progress=True,
                              backend=args.backend, address=args.address,
                              require=args.require or sweep.DEFAULT_REQUIRE)
    else:
        if not args.out:
            raise ValueError("give --out DIR for a new sweep, or --resume DIR")
        directory = Path(args.out)
        if directory.exists() and not directory.is_dir():
            raise ValueError(f"--out {args.out!r} is a file; give a folder")
        data, base_dir, table = sweep.split_sweep_table(args.scenario)
        table = table or {}
        base = sweep.scenario_from_data(data, base_dir, args.overrides)  # the base itself first
        design = sweep.design_from_args(args.grid, args.lhs, args.sobol, args.range,
                                        args.seed if args.seed is not None else base.seed, table)
        runs = args.runs if args.runs is not None else table.get("runs")
        if runs is None:
            raise ValueError("--runs N is required (cases per design point), or runs = N in the [sweep] table")
        require = args.require or table.get("require") or sweep.DEFAULT_REQUIRE
        doc = sweep.run_sweep(data, base_dir, args.overrides, design, int(runs), directory,
                              args.seed if args.seed is not None else base.seed, workers=args.workers,
                              retention=args.retention, case_timeout_s=args.case_timeout, progress=True,
                              backend=args.backend, address=args.address, require=require, dry_run=args.dry_run)
    if args.dry_run:
        print(f"dry run: {len(doc['design']['points'])} points x {doc['runs']} dispersed scenarios in "
              f"{directory / sweep.POINTS_DIR}/PPPP/cases/NNNNN/scenario.toml")
        return 0
    print(sweep.format_points(doc))
    print(f"points: {directory / sweep.POINTS_PARQUET}, cases: {directory / sweep.CASES_PARQUET}, "
          f"report: {directory / 'report.html'}")
    return 0


def cmd_faults(args: argparse.Namespace) -> int:
    if args.action not in ("list", "run"):  # `faults FILE`: the default action, on a scenario file
        if args.scenario is not None:
            raise ValueError(f"faults {args.action!r} {args.scenario!r}: the first word is list or run; allowed: "
                             "landbench faults [list|run] [SCENARIO.toml]")
        args.action, args.scenario = "run", args.action
    if args.action != "list":
        _start_workers_early(args)
    from bench.campaign import faults

    if args.action == "list":
        # Listing runs nothing: an option for the matrix given beside it would be dropped without a word.
        given = _flags_given(args, "--presets", "--runs", "--workers", "--backend", "--address", "--seed", "--out",
                             "--resume", "--retention", "--case-timeout",
                             defaults={"presets": "all", "backend": "local", "retention": "summary"})
        if given:
            raise ValueError(f"faults list prints the presets and runs nothing; drop {', '.join(given)} "
                             f"(or run the matrix: landbench faults run ...)")
        print(faults.list_presets())
        return 0
    if args.resume:
        _resume_takes_nothing_else(args, "--runs", "--seed")
        doc = faults.run_faults([], 1, Path(args.resume), None, workers=args.workers, resume=True,
                                retention=args.retention, case_timeout_s=args.case_timeout, progress=True,
                                backend=args.backend, address=args.address)
        directory = Path(args.resume)
    else:
        if not args.out:
            raise ValueError("give --out DIR for a new fault matrix, or --resume DIR")
        if args.runs is None:
            raise ValueError("--runs N is required (cases per preset)")
        presets = faults.parse_presets(args.presets)
        directory = Path(args.out)
        doc = faults.run_faults(presets, args.runs, directory, args.seed, args.scenario, args.overrides,
                                workers=args.workers, retention=args.retention, case_timeout_s=args.case_timeout,
                                progress=True, backend=args.backend, address=args.address)
    print(faults.format_matrix(doc))
    print(f"matrix: {directory / faults.MATRIX_PARQUET}, {directory / faults.FAULTS_JSON}, "
          f"{directory / faults.MATRIX_MD}; cases: {directory / faults.CASES_PARQUET}; "
          f"report: {directory / faults.REPORT}")
    return 0


def _mc_replay(directory: Path, case: int, out: Path) -> int:
    _start_helper_server()
    from bench.campaign import mc
    from bench.report.run_outputs import run_and_write

    _output_folder(str(out), "summary.json")
    meta = mc.read_meta(directory / mc.CAMPAIGN, ("campaign_seed", "runs"), "--replay")
    if not 0 <= case < meta["runs"]:
        raise ValueError(f"--case {case}: the campaign has cases 0..{meta['runs'] - 1}")
    base = load_scenario(directory / mc.BASE_SCENARIO)
    scenario, _ = mc.case_scenario(base, meta["campaign_seed"], meta["runs"], case)
    summary, table = run_and_write(scenario, out, video=True, progress=True, video_process=True, plot_process=True)
    print(table)
    return 0 if summary["landed"] else EXIT_NOT_LANDED


EXIT_GATE_FAILED = 1


def cmd_compare(args: argparse.Namespace) -> int:
    from bench.evaluation.compare import compare_campaigns, format_compare, parse_gate, write_compare
    from bench.report.compare_html import render_compare_html, write_compare_report

    out = _output_folder(args.out, "compare.json")
    gates = [parse_gate(g) for g in args.gates]  # every gate checked before the inputs are read
    doc = compare_campaigns(args.base, args.cand, gates, replay_root=out / "replay")
    html = render_compare_html(doc)  # rendered before anything is written
    written = write_compare(doc, out)  # only once every input was accepted
    report = write_compare_report(doc, out, html)
    print(format_compare(doc, written=f"{written}, {report}"))
    return 0 if doc["passed"] else EXIT_GATE_FAILED


def cmd_record(args: argparse.Namespace) -> int:
    from bench.evaluation.record import check_recordable, parse_seeds, record_dataset

    out = _output_folder(args.out, "")  # a dataset holds seed_NNN folders only: any results file is another's
    seeds = parse_seeds(args.seeds)
    for assignment in args.overrides or ():
        if assignment.partition("=")[0].strip() == "seed":
            raise ValueError(f"--set {assignment!r}: record flies each seed of --seeds, which would replace it; "
                             "give --seeds instead")
    scenario = load_scenario(args.scenario, args.overrides)
    check_recordable(scenario)
    for path, manifest in record_dataset(scenario, seeds, out, depth=args.depth, progress=True):
        c = manifest["counts"]
        size = sum(f["bytes"] for f in manifest["files"].values())
        print(f"{path}: seed {manifest['seed']}, {manifest['outcome']}, {c['control']} control ticks, "
              f"{c['image']} frames, {size / 1e6:.1f} MB")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from bench.evaluation.replay import format_replay, replay_dataset, write_replay

    out = _output_folder(args.out, "metrics.json")
    dataset = Path(args.dataset).resolve()
    if out.resolve() == dataset or dataset in out.resolve().parents:
        raise ValueError(f"--out {args.out!r} is inside the dataset being replayed; give a folder outside it")
    seqs, doc = replay_dataset(Path(args.dataset), args.overrides)  # checks every input before it runs
    written = write_replay(seqs, doc, out)
    print(format_replay(doc))
    print(", ".join(f"{k}: {v}" for k, v in written.items()))
    return 0


# --------------------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """argparse with landbench's one-line error: ``landbench: error: <what argparse found>; see 'landbench
    <command> --help'`` (argparse's own printed the usage block first, then ``landbench <command>: error:``).
    Its subparsers are of this class too (argparse makes them with the parent's class)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"landbench: error: {' '.join(message.split())}; see '{self.prog} --help'\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="landbench", description="Closed-loop lunar-landing GNC testbench (MuJoCo, vision, filterpy)."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("scenario", help="inspect scenarios")
    ssub = p.add_subparsers(dest="scenario_command", required=True, metavar="ACTION")
    ps = ssub.add_parser("show", help="print the resolved scenario as TOML")
    _add_scenario_args(ps)
    _add_preset_arg(ps)
    ps.set_defaults(func=cmd_scenario_show)

    p = sub.add_parser("run", help="fly one closed-loop landing and write its results",
                       description="Fly one landing. Exit status: 0 landed, 3 not landed, 2 bad input, 70 internal error (a defect of landbench: its traceback is printed).")
    _add_scenario_args(p)
    _add_preset_arg(p)
    p.add_argument("--out", default="out/run", help="output folder (default out/run)")
    p.add_argument("--no-video", action="store_true", help="skip camera.mp4 (then frames that vision does not use are not rendered)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("mc", help="Monte Carlo campaign of dispersed landings")
    _add_scenario_args(p)
    _add_preset_arg(p)
    p.add_argument("--runs", type=int, help="number of cases")
    p.add_argument("--workers", type=int, default=None,
                   help="cases run at once (default: 1 with local; every cluster CPU with ray)")
    p.add_argument("--backend", default="local", choices=("local", "ray"),
                   help="local: worker processes on this machine; ray: a Ray cluster (pip install 'landbench[ray]')")
    p.add_argument("--address", default=None,
                   help="Ray cluster address for --backend ray (default: $RAY_ADDRESS, else a local Ray instance)")
    p.add_argument("--seed", type=int, default=None, help="campaign seed (default: the scenario's seed)")
    p.add_argument("--out", default=None, help="campaign folder (new campaign), or replay output folder")
    p.add_argument("--resume", default=None, metavar="DIR", help="finish an interrupted campaign")
    p.add_argument("--replay", default=None, metavar="DIR", help="rerun one case of a campaign exactly")
    p.add_argument("--case", type=int, default=None, help="case index for --replay")
    p.add_argument("--dry-run", action="store_true", help="write the dispersed scenarios without running them")
    p.add_argument("--retention", default="summary", choices=("summary", "failed", "all"),
                   help="whose telemetry and video are kept")
    p.add_argument("--case-timeout", type=float, default=None, metavar="S", help="per-case wall-clock limit [s]")
    p.add_argument("--cases-per-worker", type=int, default=None, metavar="N",
                   help="cases a worker process flies before a fresh one replaces it (default 20; 1: a fresh "
                        "process per case); the rows do not depend on it")
    p.set_defaults(func=cmd_mc)

    p = sub.add_parser(
        "sweep", help="design sweep: a Monte Carlo campaign per design point (grid, Latin hypercube, Sobol)",
        description="Run a campaign of the same --runs cases (the same case seeds: common random numbers) at every "
                    "point of a design, and report each point's success rate (Wilson interval), fuel (and its ratio "
                    "to G-FOLD), p95 touchdown speeds and miss, the Pareto front among the points meeting --require, "
                    "and Sobol indices for --sobol. The design may also be a [sweep] table in the scenario file. "
                    "Every point is validated before anything runs. Writes DIR/points.parquet, DIR/cases.parquet, "
                    "DIR/sweep.json and DIR/report.html.")
    _add_scenario_args(p)
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2",
                   help="a full-factorial factor (repeatable): values, or range(start, stop, step)")
    p.add_argument("--lhs", type=int, default=None, metavar="N", help="N Latin-hypercube points over the --range factors")
    p.add_argument("--sobol", type=int, default=None, metavar="N",
                   help="Saltelli/Sobol design of N base samples over the --range factors: N (D + 2) points, "
                        "first-order and total indices (pip install 'landbench[sweep]')")
    p.add_argument("--range", action="append", default=[], metavar="KEY=LOW:HIGH",
                   help="a continuous factor for --lhs/--sobol (repeatable; integer ends give integer values)")
    p.add_argument("--runs", type=int, default=None, help="cases per design point")
    p.add_argument("--require", action="append", default=[], metavar="METRIC>=VALUE",
                   help="constraint for the Pareto front (repeatable; default success_rate>=0.95)")
    p.add_argument("--workers", type=int, default=None, help="cases run at once (as landbench mc)")
    p.add_argument("--backend", default="local", choices=("local", "ray"), help="as landbench mc")
    p.add_argument("--address", default=None, help="Ray cluster address for --backend ray")
    p.add_argument("--seed", type=int, default=None,
                   help="campaign seed, the same at every point (default: the scenario's seed); also seeds --lhs/--sobol")
    p.add_argument("--out", default=None, metavar="DIR", help="sweep folder")
    p.add_argument("--resume", default=None, metavar="DIR", help="finish an interrupted sweep")
    p.add_argument("--retention", default="summary", choices=("summary", "failed", "all"),
                   help="whose telemetry and video are kept")
    p.add_argument("--case-timeout", type=float, default=None, metavar="S", help="per-case wall-clock limit [s]")
    p.add_argument("--dry-run", action="store_true", help="write every point's dispersed case scenarios, run nothing")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser(
        "faults", help="fault presets: list them, or run each preset x N seeds (the fault matrix)",
        description="`landbench faults list` prints every preset with its provenance. `landbench faults --presets "
                    "all --runs N --out DIR` runs a Monte Carlo campaign of N cases per preset (the same case seeds "
                    "for every preset), then writes the matrix: outcome counts, success and landed-or-safe-abort "
                    "rates with Wilson intervals, fault detection rate and latency, unseen failures, false alarms "
                    "and touchdown figures: DIR/matrix.parquet, DIR/faults.json, DIR/matrix.md, DIR/cases.parquet, "
                    "DIR/report.png and each preset's campaign in DIR/presets/NAME/.")
    p.add_argument("action", nargs="?", default="run", metavar="{list,run}",
                   help="list: print the presets; run (default): the fault matrix; a scenario file in its place "
                        "runs the matrix on it")
    _add_scenario_args(p)
    p.add_argument("--presets", default="all", metavar="all|NAME,...", help="presets to run (default all)")
    p.add_argument("--runs", type=int, default=None, help="cases per preset")
    p.add_argument("--workers", type=int, default=None, help="cases run at once (as landbench mc)")
    p.add_argument("--backend", default="local", choices=("local", "ray"), help="as landbench mc")
    p.add_argument("--address", default=None, help="Ray cluster address for --backend ray")
    p.add_argument("--seed", type=int, default=None, help="campaign seed, the same for every preset "
                                                          "(default: the scenario's seed)")
    p.add_argument("--out", default=None, metavar="DIR", help="matrix folder")
    p.add_argument("--resume", default=None, metavar="DIR", help="finish an interrupted matrix")
    p.add_argument("--retention", default="summary", choices=("summary", "failed", "all"),
                   help="whose telemetry and video are kept")
    p.add_argument("--case-timeout", type=float, default=None, metavar="S", help="per-case wall-clock limit [s]")
    p.set_defaults(func=cmd_faults)

    p = sub.add_parser(
        "compare", help="paired A/B comparison of two Monte Carlo campaigns (case by case) or two replays "
                        "(sequence by sequence)",
        description="Compare CAND against BASE case by case (same case index and seed): success rates with "
                    "Wilson intervals, exact McNemar, the cases that flipped, and paired differences of every "
                    "metric (bootstrap interval, Wilcoxon, Holm). Two landbench replay folders of the same "
                    "recorded dataset compare sequence by sequence (and frame by frame), without the success "
                    "rate. Exit status: 0 all gates pass, 1 a gate "
                    "failed (named on the last line), 2 bad or unpaired input (nothing written).")
    p.add_argument("base", metavar="BASE", help="baseline campaign folder (landbench mc --out) or replay folder "
                                                "(landbench replay --out)")
    p.add_argument("cand", metavar="CAND", help="candidate folder of the same kind: a campaign with the same --runs, "
                                                "--seed and dispersions, or a replay of the same recordings")
    p.add_argument("--gate", dest="gates", action="append", default=[], metavar="SPEC",
                   help="pass/fail gate (repeatable): success_rate:-2pp, METRIC:p95:+0.05, METRIC:+10%% "
                        "(statistics: mean (default), median, p95, max; + bounds a rise, - a fall)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder: DIR/compare.json and DIR/report.html")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser(
        "record", help="fly closed-loop descents and record every message the flight software receives",
        description="For each seed, fly the landing exactly as `landbench run` does and write OUT/seed_NNN/: "
                    "the sensor messages in order, every camera frame, the truth, the telemetry and a manifest "
                    "with checksums. Replay them with `landbench replay`.")
    _add_scenario_args(p)
    p.add_argument("--seeds", required=True, metavar="SEEDS", help="seeds to fly: a range a-b or a list a,b,c")
    p.add_argument("--out", required=True, metavar="DS", help="dataset folder")
    p.add_argument("--depth", action="store_true",
                   help="also store the truth z-depth image of every frame (for truth correspondences; large)")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser(
        "replay", help="replay recorded descents open loop through the flight software (no MuJoCo, no renderer)",
        description="Feed a recorded dataset's messages to the flight software rebuilt from the recorded scenario, "
                    "with --set overrides of the tracker, vision_nav and estimator sections only, and score "
                    "navigation and tracking against the recorded truth: OUT/metrics.json, OUT/frames.parquet, "
                    "OUT/nav.parquet.")
    p.add_argument("dataset", metavar="DS", help="dataset folder (landbench record --out), or one seed_NNN folder")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override tracker.*, vision_nav.* or estimator.* (repeatable)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("render", help="render the camera view from H metres above the landing site")
    _add_scenario_args(p)
    p.add_argument("--altitude", type=float, required=True, metavar="H", help="camera height above the target [m]")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--depth", default=None, help="also write the z-depth image [m] as .npy")
    p.add_argument("--no-noise", action="store_true", help="skip the detector noise model")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("world", help="draw the terrain as a hillshade with the landing target")
    _add_scenario_args(p)
    p.add_argument("--out", required=True, help="output PNG")
    p.set_defaults(func=cmd_world)

    p = sub.add_parser("track-eval", help="score the vision tracker against truth and OpenCV on a rendered descent "
                       "or on natural textures warped by a descent")
    _add_scenario_args(p)
    p.add_argument("--imagery", choices=("descent", "textures"), default="descent",
                   help="descent: frames rendered from the simulated world (default); textures: scikit-image's "
                   "gravel, grass and brick photographs warped by known descent-like homographies (needs "
                   "scikit-image: pip install 'landbench[textures]')")
    p.add_argument("--size", type=int, action="append", choices=(256, 512),
                   help="image size [px] (repeatable; default both 256 and 512 for descent, 256 for textures)")
    p.add_argument("--frames", type=int, default=None,
                   help="frames: from the start altitude down to 30 m (descent, default 150), or per texture "
                   "(textures, default 48: 2 %% zoom per frame)")
    p.add_argument("--repeats", type=int, default=3, help="timed passes over the frames")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_track_eval)

    p = sub.add_parser("vision-figures", help="write the paper's Figs. 3-8 for rendered frames")
    _add_scenario_args(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--frames", type=int, default=60, help="frames of the rendered descent")
    p.add_argument("--start", type=int, default=None,
                   help=f"first of the three frames shown (default {DEFAULT_FIGURE_START}, or the last three of fewer frames)")
    p.set_defaults(func=cmd_vision_figures)

    p = sub.add_parser("perf", help="benchmark rendering and physics speed")
    _add_scenario_args(p)
    p.add_argument("--frames", type=int, default=60, help="frames timed per resolution")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--campaign", type=int, default=None, metavar="N",
                   help="instead: time an N-case Monte Carlo campaign at each --campaign-workers count")
    p.add_argument("--campaign-workers", default="1,2", metavar="K,K",
                   help="worker counts for --campaign (default 1,2; the first is the baseline)")
    p.add_argument("--backend", default="local", choices=("local", "ray"), help="campaign backend for --campaign")
    p.set_defaults(func=cmd_perf)
    _tag_commands(parser)
    return parser


def _tag_commands(parser: argparse.ArgumentParser) -> None:
    """Give every (sub)command's namespace its own parser (``command_parser``), so that a flag it does not know
    is reported against that command's ``--help``, not the top level's."""
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its subcommands there
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            for sub in action.choices.values():
                sub.set_defaults(command_parser=sub)
                _tag_commands(sub)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        getattr(args, "command_parser", parser).error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        return int(args.func(args) or 0)
    except ValueError as exc:  # bench.scenario.ScenarioError among them
        print(f"landbench: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:  # an output folder that cannot be made or written, a file that cannot be read
        where = f" {exc.filename!r}" if exc.filename else ""
        print(f"landbench: error: cannot write or read{where}: {exc.strerror or exc}; "
              "give a folder you can write to (or a file you can read)", file=sys.stderr)
        return EXIT_USAGE
    except SimulationDefectError as exc:  # not the user's mistake: the traceback is for the report
        traceback.print_exception(exc, file=sys.stderr)
        print(f"landbench: internal error: {exc}", file=sys.stderr)
        return EXIT_INTERNAL
    except KeyboardInterrupt:
        print("landbench: interrupted", file=sys.stderr)
        return 130


def console_main() -> int:
    """The ``landbench`` command: :func:`main` on the command line's arguments, its exit status returned.

    Before the interpreter exits, the objects still alive are frozen out of the cyclic garbage
    collector (``gc.freeze``): its last collection at shutdown would walk every object a landing
    left (about 0.15 s of a ``landbench run``); the process's memory goes back to the system whole.
    Everything the command writes is closed and renamed into place before :func:`main` returns,
    and the interpreter's exit handlers (flushing, the helper processes' shutdown) still run."""
    status = main()
    gc.freeze()
    return status


if __name__ == "__main__":
    sys.exit(console_main())
