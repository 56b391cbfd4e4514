"""Ablation grids: one run per cell, evaluated, resumable, on a local process pool or Ray.

A grid is the product of comma lists (sequences, modes, encoders, segmenters, replay on/off,
prior on/off, seeds).  Each cell is one run folder ``<root>/<cell-id>/`` (the runner's out_dir)
plus ``cell.json`` (key, status, error, ATE).

Cell ids.  A cell is keyed by everything that changes its result: the resolved config as a
canonical dict (which holds the frame cut ``data.start/frames/stride``, the seed, ``--config``
and every ``--set``) and the sequence (a named sequence's ``dataset/name``, a folder's absolute
path); keys that only change how a run is carried out (:data:`KEY_EXCLUDED`: threads,
checkpointing, results folder) are left out.  The id is a readable slug naming every axis that
was given plus the first 10 hex digits of the key's SHA-256, e.g.
``bonn-crowd__dynamic__enc-effnet-lite0__replay-on__seed0__3f9c0a1b7e``; in static mode the
motion axes do not apply and are left out (one static cell per sequence and seed).  Other
options (``--frames 20`` instead of ``--frames 10``) make other cells; the summary lists the
cells of this grid only, not every folder under the ablation's name.

Resuming.  A cell whose run.json says completed, whose cell.json holds the same key and whose
ate.json exists is skipped (a completed run without ate.json is only evaluated).  A cell folder
with a failed or interrupted run is resumed from its checkpoint.pt when there is one (``resume``;
when resuming fails it starts over) and otherwise rerun with ``overwrite=True``.  A failing cell
records its error in cell.json and the others go on.
"""

from __future__ import annotations

import hashlib
import inspect
import itertools
import json
import os
import re
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.utils.io import write_json_atomic, write_text_atomic

DEFAULT_RUNNER = "dynslam_cli.run.runner:run_sequence"
MOTION_AXES = ("encoder", "segmenter", "replay", "prior")
# config keys that change how a run is carried out, not its result: not part of a cell's key
KEY_EXCLUDED = ("run.threads", "run.checkpoint_every", "run.keep_checkpoint", "run.results_root")
KEY_DIGITS = 10


@dataclass
class Cell:
    id: str  # slug + "__" + the key's first KEY_DIGITS hex digits once keyed (key_cells); the slug before
    seq: str
    mode: str
    seed: int
    overrides: list
    axes: dict
    slug: str = ""
    key: str = ""  # SHA-256 hex of cell_key_material (empty until key_cells)

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class CellOutcome:
    id: str
    status: str  # completed | skipped | failed
    out_dir: str
    ate_rmse_m: Optional[float] = None
    rmse_still_m: Optional[float] = None
    mask_iou: Optional[float] = None
    seconds: float = 0.0
    error: str = ""


@dataclass
class AblateResult:
    name: str
    root: str
    cells: list = field(default_factory=list)  # CellOutcome
    summary_md: str = ""

    @property
    def failed(self) -> int:
        return sum(c.status == "failed" for c in self.cells)


def split_list(text: Optional[str]) -> list[str]:
    if text is None:
        return []
    return [t.strip() for t in str(text).split(",") if t.strip()]


def _onoff(values: list[str], axis: str) -> list[bool]:
    out = []
    for v in values:
        lv = v.lower()
        if lv in ("on", "true", "yes", "1"):
            out.append(True)
        elif lv in ("off", "false", "no", "0"):
            out.append(False)
        else:
            raise DynslamError(f"--{axis} takes on/off values, got '{v}'")
    return out


def seq_slug(seq: str) -> str:
    from dynslam_cli.data.names import identify

    sid = identify(seq)
    return re.sub(r"[^A-Za-z0-9._-]+", "-", f"{sid.dataset}-{sid.name}")


def build_grid(seqs: list[str], modes: list[str], encoders: list[str], segmenters: list[str],
               replay: list[str], prior: list[str], seeds: list[str], prior_file: Optional[str] = None,
               extra: Optional[list[str]] = None) -> list[Cell]:
    if not seqs:
        raise DynslamError("ablate needs at least one sequence (--seq)")
    modes = modes or ["dynamic"]
    for m in modes:
        if m not in ("dynamic", "static"):
            raise DynslamError(f"--mode takes dynamic,static; got '{m}'")
    try:
        seed_vals = [int(s) for s in (seeds or ["0"])]
    except ValueError:
        raise DynslamError(f"--seeds takes integers, got '{','.join(seeds)}'") from None
    replay_vals = _onoff(replay, "replay") if replay else [None]
    prior_vals = _onoff(prior, "prior") if prior else [None]
    if True in prior_vals:
        if not prior_file:
            raise DynslamError("--prior on needs the prior classifier file: --prior-file FILE")
        if not Path(prior_file).is_file():
            raise DynslamError(f"prior classifier file not found: {prior_file}")
    extra = list(extra or [])
    cells: dict[str, Cell] = {}
    for seq, mode, enc, seg, rep, pri, seed in itertools.product(
            seqs, modes, encoders or [None], segmenters or [None], replay_vals, prior_vals, seed_vals):
        parts = [seq_slug(seq), mode]
        ov = [f"run.mode={mode}", f"run.seed={seed}"]
        axes = {"seq": seq, "mode": mode, "seed": seed}
        if mode == "dynamic":
            ov.append("run.save_masks=true")  # eval-masks scores them where the scene has ground truth
            if enc is not None:
                parts.append(f"enc-{enc}")
                ov.append(f"motion.encoder={enc}")
                axes["encoder"] = enc
            if seg is not None:
                parts.append(f"seg-{seg}")
                ov.append(f"motion.segmenter={seg}")
                axes["segmenter"] = seg
            if rep is not None:
                parts.append(f"replay-{'on' if rep else 'off'}")
                ov.append(f"motion.replay={'true' if rep else 'false'}")
                axes["replay"] = rep
            if pri is not None:
                parts.append(f"prior-{'on' if pri else 'off'}")
                ov.append(f"motion.prior={Path(prior_file).resolve() if pri else ''}")
                axes["prior"] = pri
        parts.append(f"seed{seed}")
        slug = "__".join(re.sub(r"[^A-Za-z0-9._-]+", "-", p) for p in parts)
        cells.setdefault(slug, Cell(slug, seq, mode, seed, ov + extra, axes, slug=slug))
    return list(cells.values())


def cell_key_material(seq: str, cfg) -> dict:
    """What a cell's result depends on: the sequence and the resolved config less KEY_EXCLUDED."""
    from dynslam_cli.config.loader import config_to_dict
    from dynslam_cli.data.names import identify

    sid = identify(seq)
    conf = config_to_dict(cfg)
    for dotted in KEY_EXCLUDED:
        section, _, name = dotted.partition(".")
        (conf.get(section) or {}).pop(name, None)
    return {"sequence": str(Path(sid.path).resolve()) if sid.path is not None else sid.key, "config": conf}


def cell_key(seq: str, cfg) -> str:
    text = json.dumps(cell_key_material(seq, cfg), sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def key_cells(cells: list[Cell], config_file: Optional[str] = None, data_root: Optional[str] = None,
              frames: Optional[int] = None, preset: Optional[str] = None) -> list[Cell]:
    """Resolve every cell's config once (no data is read; bad keys or values fail before any run) and
    set its key and id.  Cells that resolve to the same key are one cell."""
    from dynslam_cli.config.resolve import resolve_config

    out: dict[str, Cell] = {}
    for cell in cells:
        cfg = resolve_config(cell.seq, config_file, list(cell.overrides), data_root=data_root, frames=frames,
                             preset=preset)
        cell.slug = cell.slug or cell.id
        cell.key = cell_key(cell.seq, cfg)
        cell.id = f"{cell.slug}__{cell.key[:KEY_DIGITS]}"
        out.setdefault(cell.key, cell)
    return list(out.values())


def _load_callable(path: str) -> Callable:
    import importlib

    mod, _, fn = path.partition(":")
    try:
        return getattr(importlib.import_module(mod), fn)
    except ModuleNotFoundError as exc:
        if mod == DEFAULT_RUNNER.split(":")[0]:
            raise DynslamError(f"the runner {path} is not available in this installation ({exc})") from None
        raise


def _cell_json(out_dir: Path) -> dict:
    try:
        d = json.loads((Path(out_dir) / "cell.json").read_text())
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}


def run_completed(out_dir: Path, key: str) -> bool:
    """The cell folder holds a completed run (run.json) of this key (cell.json)."""
    return bool(key) and runs.incomplete_reason(out_dir) is None and _cell_json(out_dir).get("key") == key


def cell_done(out_dir: Path, key: str) -> bool:
    """Completed with this key and evaluated (ate.json): nothing left to do."""
    return run_completed(out_dir, key) and (Path(out_dir) / "ate.json").is_file()


def _outcome_from_dir(cell_id: str, out_dir: Path, status: str, seconds: float = 0.0, error: str = "") -> CellOutcome:
    o = CellOutcome(cell_id, status, str(out_dir), seconds=seconds, error=error)
    ate = runs.read_result_json(out_dir / "ate.json", ("rmse_m", "rmse_still_m"))[0]
    o.ate_rmse_m, o.rmse_still_m = ate.get("rmse_m"), ate.get("rmse_still_m")
    o.mask_iou = runs.read_result_json(out_dir / "mask_metrics.json", ("mean_iou_moving",))[0].get("mean_iou_moving")
    return o


def _call_runner(run_fn: Callable, seq: str, cfg, out_dir: Path, resume: bool):
    """``run_fn(seq, cfg, out_dir, resume=..., overwrite=..., progress=False)``; ``overwrite`` only
    where the runner takes it (it refuses a folder that holds a run without it)."""
    kwargs = {"resume": resume, "progress": False}
    try:
        params = inspect.signature(run_fn).parameters
    except (TypeError, ValueError):
        params = {}
    if "overwrite" in params or any(p.kind == p.VAR_KEYWORD for p in params.values()):
        kwargs["overwrite"] = not resume
    return run_fn(seq, cfg, out_dir, **kwargs)


def execute_cell(task: dict) -> dict:
    """Run and evaluate one cell (module-level, picklable arguments only); never raises.

    ``task``: cell (Cell as dict), out_dir, config_file, data_root, frames, runner ("module:function"
    or a callable ``(spec, cfg, out_dir, resume=, overwrite=, progress=)``), threads.
    """
    cell = task["cell"]
    out_dir = Path(task["out_dir"])
    key = cell.get("key", "")
    t0 = time.time()
    if cell_done(out_dir, key):
        return asdict(_outcome_from_dir(cell["id"], out_dir, "skipped"))
    out_dir.mkdir(parents=True, exist_ok=True)
    reran = run_completed(out_dir, key)  # completed but not evaluated: evaluate only
    resume = not reran and (out_dir / "checkpoint.pt").is_file() and _cell_json(out_dir).get("key") == key
    note = ""
    write_json_atomic(out_dir / "cell.json", {"cell": cell, "key": key, "status": "running", "started": time.time()})
    try:
        threads = task.get("threads")
        if threads and task.get("worker"):  # only in a worker process: never change the caller's environment
            for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
                os.environ[var] = str(threads)
        if not reran:
            from dynslam_cli.config.resolve import resolve_config

            sets = list(cell["overrides"])
            if threads:
                sets.append(f"run.threads={threads}")
            cfg = resolve_config(cell["seq"], task.get("config_file"), sets, data_root=task.get("data_root"),
                                 frames=task.get("frames"), preset=task.get("preset"))
            if key and cell_key(cell["seq"], cfg) != key:
                raise DynslamError(f"cell {cell['id']}: its config resolves to another key than when the grid was "
                                   "built (a config file changed meanwhile?); rerun ablate")
            runner = task.get("runner") or DEFAULT_RUNNER
            run_fn = _load_callable(runner) if isinstance(runner, str) else runner
            try:
                result = _call_runner(run_fn, cell["seq"], cfg, out_dir, resume)
            except DynslamError as exc:
                if not resume:
                    raise
                note = f"resuming failed ({exc}); started over"
                result = _call_runner(run_fn, cell["seq"], cfg, out_dir, False)
            status = getattr(result, "status", None) or runs.read_run_json(out_dir).get("status")
            if status != "completed":
                raise DynslamError(f"run of cell {cell['id']} ended with status {status}")
        from dynslam_cli.eval.ate import evaluate_run_ate

        evaluate_run_ate(out_dir)
        from dynslam_cli.eval import masks

        if runs.dataset_of(out_dir) == "synth" and masks.has_masks(out_dir):
            masks.evaluate_run_masks(out_dir)
        out = _outcome_from_dir(cell["id"], out_dir, "completed", time.time() - t0, note)
    except BaseException as exc:  # noqa: BLE001 - a failing cell is recorded, the grid goes on
        if isinstance(exc, KeyboardInterrupt):
            raise
        msg = str(exc) if isinstance(exc, DynslamError) else f"{type(exc).__name__}: {exc}"
        write_json_atomic(out_dir / "cell.json", {"cell": cell, "key": key, "status": "failed", "error": msg,
                                                  "traceback": traceback.format_exc(), "seconds": time.time() - t0})
        return asdict(CellOutcome(cell["id"], "failed", str(out_dir), seconds=time.time() - t0, error=msg))
    write_json_atomic(out_dir / "cell.json", {"cell": cell, "key": key, "status": "completed", "seconds": out.seconds,
                                              "ate_rmse_m": out.ate_rmse_m, "pid": os.getpid(), "note": note})
    return asdict(out)


def _local_threads(jobs: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, jobs))


def _init_worker(threads: int) -> None:
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)


def run_local(tasks: list[dict], jobs: int, on_done: Callable[[dict], None]) -> list[dict]:
    if jobs <= 1:
        return [_tap(execute_cell(t), on_done) for t in tasks]
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    out = []
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_init_worker,
                             initargs=(tasks[0].get("threads") or 1,)) as pool:
        futs = [pool.submit(execute_cell, {**t, "worker": True}) for t in tasks]
        for f in as_completed(futs):
            out.append(_tap(f.result(), on_done))
    return out


def _tap(d: dict, fn: Callable[[dict], None]) -> dict:
    fn(d)
    return d


def run_ray(tasks: list[dict], address: Optional[str], num_cpus: Optional[int], cpus_per_cell: float,
            gpus_per_cell: float, on_done: Callable[[dict], None]) -> list[dict]:
    try:
        import ray
    except ImportError:
        raise DynslamError("the ray executor needs Ray: pip install 'dynslam_cli[ray]' (or pip install ray)") from None
    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=num_cpus or os.cpu_count(), include_dashboard=False, log_to_driver=False)
        started = True
    try:
        remote = ray.remote(num_cpus=cpus_per_cell, num_gpus=gpus_per_cell, max_retries=0)(execute_cell)
        pending = {remote.remote({**t, "worker": True}): t for t in tasks}
        out = []
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                t = pending.pop(ref)
                try:
                    d = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - worker crash: record like a failed cell
                    d = asdict(CellOutcome(t["cell"]["id"], "failed", t["out_dir"], error=f"ray task failed: {exc}"))
                out.append(_tap(d, on_done))
        return out
    finally:
        if started:
            ray.shutdown()


def summary_markdown(outcomes: list[dict]) -> str:
    def f(v, nd=4):
        return "—" if v is None else f"{v:.{nd}f}"

    lines = ["| cell | status | ATE RMSE (m) | still (m) | mask IoU | time (s) | error |",
             "|---|---|---|---|---|---|---|"]
    for o in sorted(outcomes, key=lambda o: o["id"]):
        lines.append(f"| {o['id']} | {o['status']} | {f(o['ate_rmse_m'])} | {f(o['rmse_still_m'])} | "
                     f"{f(o['mask_iou'], 3)} | {o['seconds']:.1f} | {o['error'][:80].replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def ablate(cells: list[Cell], name: str, results_root: str | Path = "results/ablations", executor: str = "local",
           jobs: int = 1, address: Optional[str] = None, config_file: Optional[str] = None,
           data_root: Optional[str] = None, frames: Optional[int] = None, runner=None,
           cpus_per_cell: float = 1.0, gpus_per_cell: float = 0.0, num_cpus: Optional[int] = None,
           on_done: Optional[Callable[[dict], None]] = None, threads: Optional[int] = None,
           preset: Optional[str] = None) -> AblateResult:
    """Run every cell (skipping finished ones) and write summary.{md,csv,json} under ``<root>/<name>/``.

    ``threads``: run.threads of each cell; default the CPUs divided by ``jobs`` (local) or
    ``cpus_per_cell`` (Ray).  The summary lists exactly the cells of this grid.
    """
    if not re.fullmatch(r"[A-Za-z0-9._-]+", name or ""):
        raise DynslamError(f"ablation name '{name}' must be letters, digits, '.', '_' or '-'")
    if executor not in ("local", "ray"):
        raise DynslamError(f"unknown executor '{executor}'; choose local or ray")
    if jobs < 1:
        raise DynslamError(f"--jobs must be at least 1, got {jobs}")
    if threads is not None and threads < 1:
        raise DynslamError(f"--threads must be at least 1, got {threads}")
    cells = key_cells(cells, config_file, data_root, frames, preset)
    root = Path(results_root) / name
    root.mkdir(parents=True, exist_ok=True)
    write_json_atomic(root / "grid.json", {"name": name, "preset": preset, "config_file": config_file, "data_root": data_root,
                                           "frames": frames, "cells": [c.to_json() for c in cells]})
    if threads is None:
        threads = _local_threads(jobs) if executor == "local" else max(1, int(cpus_per_cell))
    tasks = [{"cell": c.to_json(), "out_dir": str((root / c.id).resolve()), "config_file": config_file,
              "preset": preset, "data_root": data_root, "frames": frames, "runner": runner or DEFAULT_RUNNER, "threads": threads}
             for c in cells]
    cb = on_done or (lambda d: None)
    # finished cells are skipped here already, so a rerun of a finished grid starts no workers
    done = {t["cell"]["id"] for t in tasks if cell_done(Path(t["out_dir"]), t["cell"]["key"])}
    outcomes = [_tap(asdict(_outcome_from_dir(t["cell"]["id"], Path(t["out_dir"]), "skipped")), cb)
                for t in tasks if t["cell"]["id"] in done]
    todo = [t for t in tasks if t["cell"]["id"] not in done]
    if todo and executor == "local":
        outcomes += run_local(todo, jobs, cb)
    elif todo:
        outcomes += run_ray(todo, address, num_cpus, cpus_per_cell, gpus_per_cell, cb)
    md = summary_markdown(outcomes)
    write_text_atomic(root / "summary.md", md)
    import csv
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(CellOutcome.__dataclass_fields__))
    w.writeheader()
    for o in sorted(outcomes, key=lambda o: o["id"]):
        w.writerow(o)
    write_text_atomic(root / "summary.csv", buf.getvalue())
    write_json_atomic(root / "summary.json", sorted(outcomes, key=lambda o: o["id"]))
    return AblateResult(name, str(root), [CellOutcome(**o) for o in outcomes], md)
