"""Command line: ``python -m sghr_gtsam run|demo|sync`` (also the ``sghr-gtsam`` console script)."""

from __future__ import annotations

import errno
import os
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import typer

from sghr_gtsam.config import Config
from sghr_gtsam.errors import InputError, stopped
from sghr_gtsam.executor import _signals_held, start_server

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

    from sghr_gtsam.progress import Progress
    from sghr_gtsam.result import RunResult

app = typer.Typer(
    add_completion=False, no_args_is_help=True, help="Multiview point-cloud registration: SGHR with a GTSAM back end."
)

_DEFAULT = Config()
# Choices spelled out here so that `--help` imports nothing heavy; tests/test_review.py checks them against the
# modules.
_METHOD_NAMES = ("history", "constant", "current", "spectral", "lm")
_BASELINE_NAMES = ("eigse3", "l1_irls", "rotavg", "gnc_tls", "shonan", "open3d", "open3d_all_uncertain")
_METHOD_HELP = (
    "Synchronization method: history (SGHR's history reweighting), constant or current (its "
    "ablations), spectral (one spectral solve) or lm (spectral, then LM)."
)
_POLISH_HELP = (
    "After IRLS: loops (scans placed by counted loop evidence, then LM on the consistent edges), "
    "robust (consensus re-placement, gtsam GNC, consensus, LM), lm (LM on the edges IRLS kept) or none."
)

# The backslash keeps rich's markup from taking [ray] for a style.
_RAY_HELP = (
    "Run the parallel stages on Ray: local (a Ray instance on this machine, --workers CPUs), auto (this "
    "machine's cluster) or a head's host:port / ray://host:port. Needs pip install 'sghr_gtsam\\[ray]'."
)


def _default(value: object) -> str:
    """A help text's default for an option whose real default is None (so that a --config file's value holds),
    escaped: unescaped, rich takes '[default: …]' for markup and prints nothing."""
    from rich.markup import escape

    return " " + escape(f"[default: {value}]")


def _fail(message: str, code: int = 2) -> NoReturn:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


class _Stopped(BaseException):
    """SIGTERM (``timeout``, ``docker stop``, SLURM) or SIGINT as an exception (``_main``): a run unwinds as on
    a KeyboardInterrupt, which typer would end in a silent exit."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


@dataclass
class _Ending:
    """How the command ends: the results folder it completed (``complete``, its line on a stop after it), and from
    when nothing is left to unwind (``returned``: a stop ends the process at once, ``_end_now``), with ``code``."""

    complete: Path | None = None
    returned: bool = False
    code: int = 0


_ENDING = _Ending()


def _stop(signum: int, frame: object) -> None:
    if _ENDING.returned:
        _end_now(signum)
    raise _Stopped(signum)


def _end_now(signum: int) -> NoReturn:
    """A stop once the command has returned, while the interpreter shuts down (threads joined, exit handlers run):
    raised there, it is "ignored" with a traceback and the exit code stays 0. Its one line, and exit at once."""
    message = f"error: {stopped(signal.Signals(signum).name, _ENDING.complete and str(_ENDING.complete))}\n"
    with suppress(Exception):
        sys.stdout.flush()
    with suppress(Exception):
        os.write(2, message.encode(errors="replace"))
    os._exit(128 + signum)


def skip_teardown() -> None:
    """The last exit handler (``__main__`` registers it first): exit with the command's code without the
    interpreter's teardown, during which the signals' handlers are gone (a Ctrl-C there ended a finished run
    with 130 and no line); exit handlers registered after it have run. Not after a failure the command did not
    end itself (a traceback's exit code stays)."""
    if not _ENDING.returned:
        return
    with suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(_ENDING.code)


@contextmanager
def _guarded(out: Path | None = None, started: float = 0.0) -> Iterator[None]:
    """Bad input ends in one line on stderr and a non-zero exit, never a traceback
    (set SGHR_DEBUG=1 to see the traceback of an unexpected failure). SIGINT and SIGTERM end the command with one
    line and exit 130 / 143: what it was writing is removed, earlier outputs stay as they were; or, when the run
    of results folder ``out`` started at ``started`` (``time.time()``) has swapped its results in, the line says
    they are complete."""
    try:
        signal.signal(signal.SIGTERM, _stop)
    except ValueError:  # not the main thread: signals stay as they are
        pass
    try:
        yield
    except InputError as e:
        _fail(str(e))
    except typer.Exit:
        raise
    except (KeyboardInterrupt, _Stopped) as e:
        signum = e.signum if isinstance(e, _Stopped) else signal.SIGINT
        _fail(stopped(signal.Signals(signum).name, str(out) if _written(out, started) else None), code=128 + signum)
    except OSError as e:
        if e.errno not in (errno.ENOSPC, errno.EDQUOT) or os.environ.get("SGHR_DEBUG"):
            _unexpected(e)
        # a full disk is no fault of the tool's: say where, not "unexpected"
        _fail(f"cannot write {e.filename or out or 'the output'}: {e.strerror}", code=1)
    except Exception as e:  # noqa: BLE001 - the CLI's last line of defence
        _unexpected(e)


def _unexpected(e: Exception) -> NoReturn:
    """The line of a failure the tool did not foresee (its traceback with SGHR_DEBUG=1)."""
    if os.environ.get("SGHR_DEBUG"):
        raise e
    _fail(f"unexpected {type(e).__name__}: {e} (set SGHR_DEBUG=1 for the traceback)", code=1)


def _main(prog_name: str | None = None, arrived: Sequence[int] = ()) -> None:
    """``app`` with SIGINT and SIGTERM raised as ``_Stopped``: a KeyboardInterrupt outside ``_guarded`` ends in
    typer's silent exit 130; ``_Stopped`` ends in one line anywhere. ``arrived``: the signals that came while the
    command line was loading (``__main__``)."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _stop)
    for stream in (sys.stdout, sys.stderr):  # a latin-1 or ASCII console gets '?' for °, – and ×, not a traceback
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="replace")
    try:
        for signum in arrived[:1]:
            raise _Stopped(signum)
        app(prog_name=prog_name)
    except _Stopped as e:  # outside typer: its Exit would not end the process here
        _ENDING.returned, _ENDING.code = True, 128 + e.signum
        typer.echo(
            f"error: {stopped(signal.Signals(e.signum).name, _ENDING.complete and str(_ENDING.complete))}", err=True
        )
        sys.exit(_ENDING.code)
    except SystemExit as e:  # typer's end, always
        _ENDING.returned = True
        _ENDING.code = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
        raise


def _written(out: Path | None, started: float) -> bool:
    """Whether ``out`` holds results written since ``started``: report.json, written last, inside the staging
    folder that is swapped in whole (a rename keeps its time)."""
    try:
        return out is not None and (out / "report.json").stat().st_mtime >= started
    except OSError:
        return False


def _guard(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` under ``_guarded``."""
    with _guarded():
        return fn(*args, **kwargs)


@contextmanager
def _loading() -> Iterator[None]:
    """A command's heavy imports: guarded, with a stop held until they are done, so that Ctrl-C while they load
    ends in the same one line (an extension module interrupted in its initialisation fails as an ImportError:
    open3d's "initialization failed", with its allocator's statistics on stdout)."""
    with _guarded(), _signals_held():
        yield


def _config(config_file: Path | None, **overrides) -> Config:
    cfg = Config.from_json(config_file) if config_file else Config()
    for key, value in overrides.items():
        if value is not None:
            setattr(cfg, key, value)
    return cfg.validate()


def _start_workers(cfg: Config) -> None:
    """Start the parallel stages' fork server before importing the pipeline (torch, gtsam, rerun: seconds), so
    that both import at once on two cores."""
    from sghr_gtsam.registration import WORKER_MODULES

    start_server(WORKER_MODULES, cfg.workers, cfg.ray)


def _observed(run_pipeline, quiet: bool, scene_dir: Path, out: Path, cfg: Config, started: float) -> RunResult:
    """``run_pipeline(scene_dir, out, cfg)`` under ``_guarded(out, started)`` with the terminal's progress: bars
    with their ETA and the stage messages above them on a terminal; the messages alone when the output is no
    terminal; nothing with ``--quiet``."""
    from sghr_gtsam.progress import QUIET

    progress: Progress = QUIET
    log = typer.echo
    if quiet:
        log = _silent
    elif sys.stdout.isatty() and sys.stderr.isatty():
        from sghr_gtsam.progress import TerminalProgress

        progress = TerminalProgress(_console())
        log = progress.log

    with _guarded(out, started):
        try:
            return run_pipeline(scene_dir, out, cfg, log=log, progress=progress)
        finally:
            progress.close()  # before an error is printed, so that it lands below the bars, on stderr


def _silent(message: str) -> None:
    return None


def _console() -> Console:
    from rich.console import Console

    return Console(highlight=False)


def _names(names: list[str], shown: int = 4) -> str:
    from sghr_gtsam.io.poses import shown_name

    return ", ".join(map(shown_name, names[:shown])) + (f" (+{len(names) - shown} more)" if len(names) > shown else "")


def _summary_table(result: RunResult, out: Path) -> Table:
    """The closing summary of a run: scans placed and verified, the worst residual among the edges the result
    rests on, and the seconds of each stage (the parts follow it, ``_close``)."""
    import numpy as np
    from rich.table import Table

    n = len(result.names)
    table = Table(title=f"{out}", title_justify="left", show_header=False, box=None, padding=(0, 2, 0, 0))
    table.add_column(style="bold")
    table.add_column()
    table.add_row("scans placed", f"{len(result.registered)}/{n}")
    if result.verdict is not None:
        status = list(result.verdict.status.values())
        table.add_row(
            "verified",
            f"{status.count('verified')}, doubtful {status.count('doubtful')}, in {len(result.verdict.parts)} part(s)",
        )
    skipped = list(result.skipped)
    table.add_row("skipped files", f"{len(skipped)}" + (f": {_names(skipped)}" if skipped else ""))
    g, s = result.graph, result.sync
    kept = np.flatnonzero(s.weights > 0)
    table.add_row("edges kept", f"{len(kept)} of {g.num_edges} registered pairs")
    if len(kept):
        e = kept[np.argmax(s.residual_deg[kept])]
        table.add_row(
            "worst residual",
            f"{s.residual_deg[e]:.2f}° ({result.names[g.i[e]]} – {result.names[g.j[e]]}, rotation, among kept edges)",
        )
    stages = [f"{name} {seconds:.1f}" for name, seconds in result.timings.items() if name != "total"]
    table.add_row("seconds", f"{result.timings.get('total', 0.0):.1f} total: " + " · ".join(stages))
    return table


def _close(result: RunResult, out: Path, recorded: bool) -> None:
    """Print the summary table, one line per part (stderr when some scan is doubtful) and how to open the
    recording."""
    console = _console()
    if console.is_terminal:
        console.print(_summary_table(result, out))
    else:  # a log file gets the table without the padding rich puts at the end of its lines
        with console.capture() as table:
            console.print(_summary_table(result, out))
        typer.echo("\n".join(line.rstrip() for line in table.get().splitlines()))
    if result.verdict is not None:
        doubtful = bool(result.verdict.doubts) or len(result.verdict.parts) > 1 or bool(result.unregistered)
        for line in result.verdict.summary():
            typer.echo(line, err=doubtful)
    typer.echo(f"summary picture: {out / 'summary.png'}")
    if recorded:
        typer.echo(f"review the run: rerun {out / 'recording.rrd'}")


@app.command()
def run(
    scene_dir: Path = typer.Argument(
        ..., help="Folder of scans (.ply .pcd .xyz .txt .npy .npz .las .laz .e57); order = natural order of the names."
    ),
    out: Path | None = typer.Option(None, "--out", help="Results folder." + _default("results/<scene name>")),
    voxel: float | None = typer.Option(
        None, help="Voxel size in scene units." + _default("1/100 of the median scan's bounding-box diagonal")
    ),
    k: int | None = typer.Option(None, help="Top-k partners per scan (10 indoor, 6 outdoor)." + _default(_DEFAULT.k)),
    iters: int | None = typer.Option(None, help="IRLS iterations M (history reweighting)." + _default(_DEFAULT.iters)),
    method: str | None = typer.Option(None, help=_METHOD_HELP + _default(_DEFAULT.method)),
    polish: str | None = typer.Option(None, help=_POLISH_HELP + _default(_DEFAULT.polish)),
    global_feature: str | None = typer.Option(
        None,
        help="Overlap scores: vlad (scene codebook) or learned (shipped head)." + _default(_DEFAULT.global_feature),
    ),
    descriptor: str | None = typer.Option(
        None,
        help="Local descriptor pairs are matched on: fpfh or learned "
        "(trained on simulated rooms; more pairs right on 3DMatch, slower)." + _default(_DEFAULT.descriptor),
    ),
    features: str | None = typer.Option(
        None,
        "--features",
        help="Folder of precomputed features per scan: <stem>.kpts.npy (Kx3, scan frame) and <stem>.desc.npy (KxD), "
        "also in sub-folders; they replace FPFH. Scans without them are skipped.",
    ),
    overlap_head: Path | None = typer.Option(
        None,
        "--overlap-head",
        help="NetVLAD overlap head checkpoint (e.g. the SGHR authors' netvlad_overlap_model_best.pth for YOHO); "
        "given, it scores the overlaps.",
    ),
    seed: int | None = typer.Option(None, help="Seed of every random choice." + _default(_DEFAULT.seed)),
    max_sigma: float | None = typer.Option(
        None,
        "--max-sigma",
        help="Largest σ (scene units) along a direction "
        "only the overlap's bounds fix for which a scan is not doubted as "
        "loose." + _default("the registrations' agreement tolerance"),
    ),
    workers: int | None = typer.Option(
        None,
        help="Processes for local features, pairwise registration, "
        "refinement and loop closure." + _default("every core"),
    ),
    ray: str | None = typer.Option(
        None, "--ray", metavar="ADDRESS", help=_RAY_HELP + _default("none: local processes")
    ),
    record: bool | None = typer.Option(
        None, "--record/--no-record", help="Write recording.rrd for the Rerun viewer." + _default("--record")
    ),
    cache: bool | None = typer.Option(
        None,
        "--cache/--no-cache",
        help="Keep features and pair registrations in "
        "OUT/cache and reuse them: a stopped run started again redoes only what is "
        "missing." + _default("--cache"),
    ),
    config_file: Path | None = typer.Option(
        None, "--config", help="A config.json from an earlier run; options given here override it."
    ),
    quiet: bool = typer.Option(
        False,
        "--quiet",
        "-q",
        help="No progress bars and no stage messages: only the "
        "closing summary and warnings (bars are also off when the output is no terminal).",
    ),
) -> None:
    """Register every scan of SCENE_DIR into one frame and write the results folder."""
    cfg = _guard(
        _config,
        config_file,
        voxel=voxel,
        k=k,
        iters=iters,
        method=method,
        polish=polish,
        seed=seed,
        max_sigma=max_sigma,
        workers=workers,
        ray=ray,
        record=record,
        cache=cache,
        global_feature=global_feature,
        descriptor=descriptor,
        features=features,
        overlap_head=overlap_head and str(overlap_head),
    )
    with _loading():
        _start_workers(cfg)
        from sghr_gtsam.pipeline import run as run_pipeline

    out = out or Path("results") / scene_dir.resolve().name
    started = time.time()
    result = _observed(run_pipeline, quiet, scene_dir, out, cfg, started)
    _ENDING.complete = out
    with _guarded(out, started):
        _close(result, out, cfg.record)


# synthetic.SCENE_KINDS, spelled out as _METHOD_NAMES are
_SCENE_KINDS = ("room", "object", "fragments", "building", "hotel")
_ONE_ROOM = 12  # --kind auto: the most scans it generates as one room
_DEMO_ROWS = 40  # the most scans the demo lists one by one
_MOST_SCANS = 10_000
"""The most scans ``demo`` generates: the run's main process grows by ~1.3 MB a scan (its pairs' state, two N × N
matrices: bounded memory in the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md),
~13 GB at 10,000; 2,000 took 46 min on 2 cores."""


def _scene_kind(kind: str, scans: int) -> str:
    if kind == "auto":
        return "room" if scans <= _ONE_ROOM else "building"
    if kind not in _SCENE_KINDS:
        raise InputError(f"--kind must be auto or one of {', '.join(_SCENE_KINDS)}; got {kind!r}")
    return kind


def _check_demo_folders(out: Path) -> None:
    """``InputError`` unless ``out/scene`` and ``out/results``, which the demo replaces, are new, empty or its own
    earlier output: a scene ``synthetic.written_scene`` recognises (its gt_poses.txt and the scans it names, nothing
    else), and beside it a run's results (``io.results.check_output_folder``)."""
    from sghr_gtsam.io.results import check_output_folder, check_output_path
    from sghr_gtsam.synthetic import written_scene

    scene, results = out / "scene", out / "results"
    check_output_path(scene)
    ours = written_scene(scene)
    if os.path.lexists(scene) and not ours and not _empty_folder(scene):
        raise InputError(
            f"--out {out}: {scene} holds files the demo did not write (it writes generated scans and "
            f"gt_poses.txt, and replaces that folder as a whole); choose a new or empty --out"
        )
    if os.path.lexists(results) and not _empty_folder(results):
        if not ours:
            raise InputError(
                f"--out {out}: {results} is not the demo's (no scene it generated beside it), and the "
                f"demo replaces it as a whole; choose a new or empty --out"
            )
        check_output_folder(results, scene)


def _empty_folder(path: Path) -> bool:
    try:
        return path.is_dir() and not any(path.iterdir())
    except OSError:
        return False


@app.command()
def demo(
    out: Path = typer.Option(Path("results/demo"), "--out", help="Where the generated scene and the results go."),
    scans: int = typer.Option(8, help="Number of generated scans."),
    kind: str = typer.Option(
        "auto",
        help="Generated scene: room (one furnished room scanned from around its "
        "table), object (a lumpy object seen from around it), fragments (the room seen by a walking "
        "depth camera, each scan fused from its frames, as RGB-D fragments are), building (furnished rooms along "
        "corridors, growing with --scans so that each scan overlaps a bounded number of others; "
        "at least 9 scans), hotel (the building with every room the same: scans that fit "
        f"several places) or auto (room up to {_ONE_ROOM} scans, building above).",
        show_default=True,
    ),
    seed: int = typer.Option(0, help="Seed of the generated scene and of the run."),
    workers: int | None = typer.Option(None, help="Processes for the parallel stages." + _default("every core")),
    ray: str | None = typer.Option(
        None, "--ray", metavar="ADDRESS", help=_RAY_HELP + _default("none: local processes")
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars and no stage messages."),
) -> None:
    """Generate a scene scanned from several stations (known poses), register it, print the errors."""
    with _loading():
        from sghr_gtsam.evaluate import scan_errors, whole_model_errors
        from sghr_gtsam.io.atomic import staged_folder
        from sghr_gtsam.io.poses import read_poses
        from sghr_gtsam.pipeline import run as run_pipeline
        from sghr_gtsam.synthetic import make_scene, write_scene

    cfg = _guard(_config, None, seed=seed, workers=workers, ray=ray)

    def generate() -> Path:
        if scans < 2:
            raise InputError(f"--scans must be at least 2 (a registration needs two scans); got {scans}")
        if scans > _MOST_SCANS:
            raise InputError(
                f"--scans must be at most {_MOST_SCANS:,} (the run's memory grows with the scans and "
                f"their pairs: ~13 GB at {_MOST_SCANS:,}); got {scans:,}"
            )
        if out.exists() and not out.is_dir():
            raise InputError(f"--out {out} is an existing file, not a folder")
        _check_demo_folders(out)
        scene_kind = _scene_kind(kind, scans)
        try:
            scene = make_scene(kind=scene_kind, n_scans=scans, seed=seed)
        except ValueError as e:  # too few scans for the kind
            raise InputError(f"--scans {scans}: {e}") from None
        scene_dir = out / "scene"
        with staged_folder(scene_dir) as stage:  # replaced as a whole: no scan of an earlier, larger demo stays
            write_scene(scene, stage)  # a building's scans are made one at a time as they are written
        return scene_dir

    scene_dir = _guard(generate)
    started = time.time()
    result = _observed(run_pipeline, quiet, scene_dir, out / "results", cfg, started)
    _ENDING.complete = out / "results"
    with _guarded(out / "results", started):
        gt_names, gt = read_poses(scene_dir / "gt_poses.txt")
        gt = gt[[gt_names.index(n) for n in result.names]]
        err = scan_errors(result.names, result.poses, gt)
        flags = result.verdict.doubts if result.verdict is not None else {}
        good = err.within(5.0, 0.2)
        listed = [
            k for k, name in enumerate(result.names) if len(result.names) <= _DEMO_ROWS or name in flags or not good[k]
        ]
        typer.echo(f"{'scan':<16}{'rot err [deg]':>15}{'trans err [m]':>15}")
        for k in listed:
            name = result.names[k]
            flag = f"  ({flags[name]})" if name in flags else ""
            typer.echo(f"{name:<16}{err.rotation_deg[k]:>15.3f}{err.translation[k]:>15.4f}{flag}")
        if len(listed) < len(result.names):
            typer.echo(
                f"({len(result.names) - len(listed)} more scans within 5° / 0.2 m of GT relative to "
                f"{result.names[0]}, none flagged)"
            )
        placed = [k for k, name in enumerate(result.names) if name not in result.unregistered]
        whole = whole_model_errors([result.names[k] for k in placed], result.poses[placed], gt[placed])
        typer.echo(
            f"{int(whole.within(5.0, 0.2).sum())} of {len(result.names)} scans within 5° / 0.2 m of GT after "
            f"one rigid alignment of the placed scans (ATE {whole.ate_rmse:.3f} m)"
        )
        _close(result, out / "results", cfg.record)


@app.command()
def sync(
    graph_file: Path = typer.Argument(..., help="A 3D g2o pose graph (VERTEX_SE3:QUAT, EDGE_SE3:QUAT)."),
    out: Path = typer.Option(
        ...,
        "--out",
        help="Where to write the optimized g2o graph (same vertex ids) with the "
        "edges it rests on; the dropped edges go beside it, to OUT's name with _rejected.",
    ),
    method: str = typer.Option(
        _DEFAULT.method, help=_METHOD_HELP + " Or a baseline: " + ", ".join(_BASELINE_NAMES) + ".", show_default=True
    ),
    iters: int = typer.Option(_DEFAULT.iters, help="IRLS iterations M (reweighting methods).", show_default=True),
    polish: str = typer.Option(
        _DEFAULT.polish, help=_POLISH_HELP + " Method lm always ends with LM.", show_default=True
    ),
    noise: str = typer.Option(
        _DEFAULT.noise_model,
        help="information: each edge's own 6x6 information; "
        "isotropic: SE-Sync's precisions (2κ rotation, τ translation).",
        show_default=True,
    ),
    kernel: str = typer.Option(
        _DEFAULT.kernel,
        help="Robust kernel of a final gtsam pass over the kept edges: none (no pass), huber, cauchy or tls (GNC).",
        show_default=True,
    ),
) -> None:
    """Synchronize a pose graph read from a g2o file; write the optimized vertices with the edges they rest on to
    OUT, and the dropped edges beside it (OUT's name with "_rejected": edges only, as a run's graph_rejected.g2o)."""
    with _loading():
        import numpy as np

        from sghr_gtsam.gtsam_api import KERNELS, NOISE_MODELS, check_choice, repolish
        from sghr_gtsam.io.g2o import fixed_ids, isotropic_information, read_g2o, sesync_objective, write_g2o
        from sghr_gtsam.sync import checked_graph, synchronize, unverified

    def work() -> None:
        check_choice("--noise", noise, NOISE_MODELS)
        check_choice("--kernel", kernel, KERNELS)
        check_choice("--method", method, _METHOD_NAMES + _BASELINE_NAMES)
        rejected = _rejected_path(out)
        _refuse_overwriting(graph_file, out, rejected)
        ids, given, graph = read_g2o(graph_file, positive_definite=True, indefinite=noise == "isotropic")
        given_information = graph.information
        if noise == "isotropic":
            _warn_indefinite(graph_file, graph.information)
            graph = replace(graph, information=isotropic_information(graph.information))
        try:
            checked = checked_graph(graph)
        except InputError as e:  # said of the file: its line, not the graph's edge index
            raise InputError(_in_file(str(e), graph_file)) from None
        if method in _BASELINE_NAMES:
            from sghr_gtsam.sync.baselines import BASELINES

            result = BASELINES[method](checked)
        else:
            result = synchronize(graph, method=method, iters=iters, polish=polish)
        kept = result.weights > 0
        if kernel != "none":
            result.poses = repolish(graph, result.poses, kept, result.component, kernel=kernel)
        index = {v: k for k, v in enumerate(ids)}
        poses, free = _in_input_frame(
            result.poses, result.component, given, [index[v] for v in fixed_ids(graph_file) if v in index]
        )
        # What the result rests on, with the input's own information (not the isotropic one a solve used).
        given_graph = replace(graph, information=given_information)
        write_g2o(rejected, ids, None, _edges(given_graph, ~kept), indefinite=True)
        write_g2o(out, ids, poses, _edges(given_graph, kept), indefinite=True)
        parts = int(result.component.max()) + 1
        typer.echo(
            f"{graph.n} poses, {graph.num_edges} edges: {int(kept.sum())} kept -> {out}, "
            f"{int((~kept).sum())} dropped -> {rejected}; {parts} connected part(s); SE-Sync objective over "
            f"the kept edges {sesync_objective(poses, _edges(graph, kept)):.6g}"
        )
        apart = [ids[k] for k in np.flatnonzero(result.component > 0)]
        if apart:
            shown = " ".join(map(str, apart[:10])) + (" ..." if len(apart) > 10 else "")
            typer.echo(
                f"{len(apart)} pose(s) outside the largest part, joined to it by no kept edge: each part is "
                f"placed by its first vertex's input pose, not by the graph: {shown}",
                err=True,
            )
        if free:
            typer.echo(
                f"FIX vertices placed by the graph (a part is held at its first FIX vertex): "
                f"{' '.join(str(ids[k]) for k in free)}",
                err=True,
            )
        weak = [ids[k] for k in np.flatnonzero(unverified(graph, result))]
        if weak:
            shown = " ".join(map(str, weak[:10])) + (" ..." if len(weak) > 10 else "")
            typer.echo(
                f"{len(weak)} pose(s) of the largest part unverified (reached across an edge on no loop or "
                f"through one node): {shown}",
                err=True,
            )

    _guard(work)


def _rejected_path(out: Path) -> Path:
    """Where ``sync --out OUT`` writes the edges it dropped: OUT's name with ``_rejected`` before its suffix."""
    return out.with_name(f"{out.stem}_rejected{out.suffix}")


def _refuse_overwriting(graph_file: Path, *outputs: Path) -> None:
    """A one-line ``InputError`` if an output is the input file itself (the same path, or a link to it)."""
    for path in outputs:
        try:
            same = os.path.samefile(graph_file, path)
        except OSError:  # either does not exist (a missing input is the reader's to say)
            same = False
        if same:
            raise InputError(f"{path} is the input file {graph_file}: choose another --out")


def _warn_indefinite(graph_file: Path, information) -> None:
    """For ``--noise isotropic``: a one-line ``InputError`` naming the first edge whose rotation or translation block
    is not positive definite (SE-Sync's precisions need both), and a warning naming those whose whole information
    is not, which the isotropic precisions do not use."""
    import numpy as np

    from sghr_gtsam.io.g2o import edge_line, isotropic_ready, not_definite

    unusable = np.flatnonzero(~isotropic_ready(information))
    if len(unusable):
        raise InputError(
            f"{graph_file}: line {edge_line(graph_file, int(unusable[0]))}: information's rotation or "
            f"translation block is not positive definite, which --noise isotropic needs"
        )
    odd = np.flatnonzero(not_definite(information))
    if len(odd):
        lines = [str(edge_line(graph_file, int(e))) for e in odd[:10]]
        more = f" and {len(odd) - 10} more" if len(odd) > 10 else ""
        typer.echo(
            f"warning: {graph_file}: information matrix not positive definite on line(s) {' '.join(lines)}"
            f"{more}: used through its blocks' isotropic precisions (--noise isotropic), written out as given",
            err=True,
        )


def _edges(graph, chosen):
    """``graph`` (a ``PoseGraph``) with only the ``chosen`` (E,) edges."""
    info = None if graph.information is None else graph.information[chosen]
    return replace(
        graph, i=graph.i[chosen], j=graph.j[chosen], T=graph.T[chosen], weight=graph.weight[chosen], information=info
    )


def _in_file(message: str, path: Path) -> str:
    """A graph check's ``message`` about g2o file ``path``: "edge K: …" named by the line of its K-th edge."""
    import re

    from sghr_gtsam.io.g2o import edge_line

    found = re.match(r"edge (\d+): ", message)
    if not found:
        return f"{path}: {message}"
    line = edge_line(path, int(found[1]))
    return f"{path}: line {line}: {message[found.end() :]}" if line else f"{path}: {message}"


def _in_input_frame(poses, component, given, fixed):
    """``poses`` (N, 4, 4) of each connected part (``component``) moved rigidly so that its anchor keeps its
    ``given`` input pose: its first vertex in ``fixed`` (node indices of the file's ``FIX`` lines), else its first
    vertex; the input frame, as a prior on that pose at its initial value holds it in gtsam. Synchronization anchors
    every part at the identity, which stacked the parts on one another. Also the fixed vertices left free (a part
    holds one)."""
    import numpy as np

    from sghr_gtsam.se3 import inv_T

    anchor = np.unique(component, return_index=True)[1]  # each part's first vertex, by its label
    held, free = set(), []
    for k in fixed:
        if component[k] in held:
            free.append(k)
        else:
            held.add(component[k])
            anchor[component[k]] = k
    a = anchor[component]
    return given[a] @ inv_T(poses[a]) @ poses, free


@app.command(
    "train", context_settings={"allow_extra_args": True, "ignore_unknown_options": True}, add_help_option=False
)
def train(ctx: typer.Context) -> None:
    """Train the NetVLAD overlap head on simulated scans (see `train --help`)."""
    with _loading():
        from sghr_gtsam.train import train_command  # torch training code loads only for this command

    sub = typer.Typer(add_completion=False)
    sub.command()(train_command)
    _guard(sub, ctx.args, prog_name="python -m sghr_gtsam train")
