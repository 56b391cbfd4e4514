"""`dynslam tables`: paper-style tables and plots from result files only.

Reads every run folder (a folder holding ``run.json``) under the results folder -- plain runs
(``runs/<dataset>/<sequence>/<variant>/``) and ablation cells (``ablations/<name>/<cell>/``) --
and writes ``<out>/<table>.{csv,md,tex}`` plus ``<out>/plots/*.png`` and ``<out>/README.md``.

Files read per run: run.json (status, sequence.dataset/name/path, mode, seed, frames),
config.yaml (motion settings: encoder, segmenter, replay, prior; the cut data.start/frames/
stride), the sequence's rgb.txt (its full length), ate.json, mesh_metrics.json, timing.json
(``mean_ms``, ``calls``, ``frames``, ``fps``), classifier_updates.jsonl (one line per update; its
``frame``/``index``/``timestamp`` field, else the line number, places it in time), masks/<ts>.png
and, when present, renders/<ts>_depth.png and the sequence's input images, found through its
rgb.txt/depth.txt (montage).

Only runs whose run.json says ``completed`` count (``include_incomplete`` takes the others too);
a skipped run, and a result file that cannot be used (not JSON, not an object, a number that is
not one), is one warning line, and the tables are made from the rest.

Values are the mean ± sample std over distinct seeds, with n (runs with the same seed are
averaged first: repeats are not a spread); '—' where nothing exists.  Counts print as integers.
The best value of a row is bold in Markdown/LaTeX and named in the CSV's ``best`` column.

Frames.  Each row is one sequence and one cut: whole-sequence runs share the sequence's row
(frames column ``all (N)``), runs on a clip (data.start > 0, stride > 1, or fewer frames than
the sequence) get a row of their own, ``bonn/crowd [frames 150–448 step 2]``, whose frames
column says ``300 of 1159`` (or ``clip of 300 frames`` when the sequence's length is unknown).
Published numbers are on full sequences and are only shown on whole-sequence rows.

Which runs feed which table:

* Table 1 (ATE): "ours dynamic" pools dynamic runs at the default motion settings (encoder,
  segmenter and replay as the config defaults, no prior); "ours static" pools static runs;
  "still camera" is ``rmse_still_m`` of those runs (see eval/ate.py); the published columns come
  from configs/published.yaml.  The best of a row is taken over the method columns (not still).
* Encoder / prior / replay ablations: each varies one axis and pools the dynamic runs whose other
  motion axes are at their defaults.
* Run-time: per component, the mean per frame (timing.json ``mean_ms``) and per call (the mean
  over the frames on which it ran: ``mean_ms × frames / calls[component]``; bundle adjustment runs
  every mapping.every-th frame, so its median per frame is 0 and says nothing).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.eval.plots import montage, plot_updates
from dynslam_cli.utils.io import write_text_atomic

DASH = "—"
PUBLISHED_METHODS = ("ReFusion", "StaticFusion", "DynaSLAM", "Co-SLAM")


# ---------------------------------------------------------------- reading runs
@dataclass
class RunRecord:
    path: Path
    seq: str
    mode: str
    seed: int
    encoder: str
    segmenter: str
    replay: bool
    prior: bool
    ate: Optional[float] = None
    still: Optional[float] = None
    mesh: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)  # mean ms per frame, per component (timing.json mean_ms)
    fps: Optional[float] = None
    updates: Optional[list] = None  # positions in time of each classifier update
    frames: Optional[int] = None  # frames the run processed (run.json frames)
    start: int = 0  # the cut (config.yaml data.start / data.frames / data.stride)
    cut_frames: int = 0
    stride: int = 1
    total_frames: Optional[int] = None  # frames of the whole sequence (its rgb.txt), when known
    timing_calls: dict = field(default_factory=dict)  # frames on which each component ran (timing.json calls)
    timing_frames: Optional[int] = None  # timing.json frames
    status: str = "completed"

    @property
    def clip(self) -> bool:
        """A run on a part of the sequence (the cut skips frames), not comparable to full-sequence numbers."""
        if self.start > 0 or self.stride > 1:
            return True
        if self.cut_frames > 0:
            return self.total_frames is None or self.cut_frames < self.total_frames
        return False

    @property
    def cut(self) -> Optional[tuple]:
        """None for a full-sequence run, else (start, frames, stride): runs of one cut pool in one row."""
        return (self.start, self.frames, self.stride) if self.clip else None


def _updates(path: Path) -> tuple[Optional[list], Optional[str]]:
    if not path.is_file():
        return None, None
    out = []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        return None, f"{path}: not readable ({exc})"
    for i, line in enumerate(text.splitlines()):
        if not line.strip():
            continue
        try:
            d = json.loads(line)
        except json.JSONDecodeError:
            return None, f"{path}: line {i + 1} is not JSON"
        pos = i
        if isinstance(d, dict):
            for k in ("frame", "index", "timestamp"):
                if runs.is_number(d.get(k)):
                    pos = d[k]
                    break
        out.append(pos)
    return out, None


def _int(value, default: Optional[int]) -> Optional[int]:
    if isinstance(value, bool):
        return default
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return default


def sequence_frames(run_dir: Path, meta: dict) -> Optional[int]:
    """Frames of the whole sequence: the lines of its rgb.txt (None when the folder is not here)."""
    from dynslam_cli.data.tum import read_file_list

    sp = runs.sequence_path(run_dir, meta)
    if sp is None or not (sp / "rgb.txt").is_file():
        return None
    try:
        return len(read_file_list(sp / "rgb.txt"))
    except DynslamError:
        return None


def read_run(run_dir: Path, warnings: Optional[list] = None, include_incomplete: bool = False) -> Optional[RunRecord]:
    """The run's record; None (and a line in ``warnings``) for a run that is not completed (unless
    ``include_incomplete``) or whose run.json / config.yaml is unusable.  A bad result file
    (ate.json, mesh_metrics.json, timing.json, classifier_updates.jsonl) is left out with a warning."""
    import dynslam_cli.config  # noqa: F401 - the config package first (avoids a circular import)
    from dynslam_cli.motion.config import MotionConfig

    warnings = warnings if warnings is not None else []
    reason = runs.incomplete_reason(run_dir, include_incomplete)
    if reason is not None:
        warnings.append(f"skipped: {reason}")
        return None
    try:
        meta = runs.read_run_json(run_dir, required=True)
        config = runs.read_run_config(run_dir)
    except DynslamError as exc:
        warnings.append(f"skipped run {run_dir}: {exc}")
        return None
    seq = runs.sequence_info(run_dir, meta)
    key = f"{seq.get('dataset', '?')}/{seq.get('name', run_dir.name)}"
    sections = {k: (config.get(k) if isinstance(config.get(k), dict) else {}) for k in ("motion", "run", "data")}
    motion, cfg_run, data = sections["motion"], sections["run"], sections["data"]
    seed = _int(meta.get("seed", cfg_run.get("seed", 0)), None)
    if seed is None:
        warnings.append(f"skipped run {run_dir}: run.json seed is not an integer ({meta.get('seed')!r})")
        return None
    dm = MotionConfig()
    rec = RunRecord(
        path=run_dir, seq=key, mode=str(meta.get("mode") or cfg_run.get("mode") or "dynamic"), seed=seed,
        encoder=str(motion.get("encoder", dm.encoder)), segmenter=str(motion.get("segmenter", dm.segmenter)),
        replay=bool(motion.get("replay", dm.replay)), prior=bool(motion.get("prior", dm.prior)),
        frames=_int(meta.get("frames"), None), start=max(0, _int(data.get("start"), 0)),
        cut_frames=max(0, _int(data.get("frames"), 0)), stride=max(1, _int(data.get("stride"), 1)),
        total_frames=sequence_frames(run_dir, meta), status=str(meta.get("status")),
    )

    def result(name: str, numbers: tuple = (), maps: tuple = ()) -> dict:
        d, problem = runs.read_result_json(run_dir / name, numbers, maps)
        if problem:
            warnings.append(f"skipped file {problem}")
        return d

    ate = result("ate.json", ("rmse_m", "rmse_still_m"))
    rec.ate, rec.still = ate.get("rmse_m"), ate.get("rmse_still_m")
    rec.mesh = result("mesh_metrics.json", ("accuracy_m", "completion_m", "completion_ratio"))
    timing = result("timing.json", ("fps", "frames"), ("mean_ms", "median_ms", "calls"))
    rec.timing = dict(timing.get("mean_ms") or {})
    rec.timing_calls = dict(timing.get("calls") or {})
    rec.timing_frames = _int(timing.get("frames"), None)
    rec.fps = timing.get("fps")
    rec.updates, problem = _updates(run_dir / "classifier_updates.jsonl")
    if problem:
        warnings.append(f"skipped file {problem}")
    return rec


def collect_runs(results: Path, warnings: Optional[list] = None, include_incomplete: bool = False) -> list[RunRecord]:
    """Records of the run folders (holding run.json) under ``results``; see :func:`read_run`."""
    if not results.is_dir():
        raise DynslamError(f"results folder not found: {results}")
    recs = []
    for rj in sorted(results.rglob("run.json")):
        if "tables" in rj.relative_to(results).parts[:1]:
            continue
        r = read_run(rj.parent, warnings, include_incomplete)
        if r is not None:
            recs.append(r)
    return recs


def load_published(path: Optional[Path] = None) -> dict:
    import yaml

    from dynslam_cli.config import configs_dir

    path = path or configs_dir() / "published.yaml"
    if not path.is_file():
        raise DynslamError(f"published numbers file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise DynslamError(f"corrupt {path}: {exc}") from None
    return data


# ---------------------------------------------------------------- table model
@dataclass
class Cell:
    text: str = DASH
    value: Optional[float] = None


@dataclass
class Table:
    name: str
    title: str
    columns: list
    rows: list = field(default_factory=list)  # (label, [Cell])
    best: list = field(default_factory=list)  # [(column indices, lower_is_better)]
    notes: list = field(default_factory=list)

    def best_cols(self, cells: list) -> set:
        out = set()
        for cols, lower in self.best:
            vals = [(cells[i].value, i) for i in cols if cells[i].value is not None and math.isfinite(cells[i].value)]
            if len(vals) < 2:
                continue
            target = min(v for v, _ in vals) if lower else max(v for v, _ in vals)
            out |= {i for v, i in vals if v == target}
        return out


def _fmt(v: float, nd: int, integer: bool) -> str:
    if integer and float(v).is_integer():
        return str(int(v))
    return f"{v:.{1 if integer else nd}f}"


def stat_cell(pairs: list, scale: float = 1.0, nd: int = 3, integer: bool = False) -> Cell:
    """Mean ± sample std over distinct seeds of ``[(seed, value), ...]``.

    Runs with the same seed are averaged first (they are repeats, not a spread); ``n`` counts the
    seeds, and the runs too where there are more runs than seeds: ``0.022 (n=1 seed, 2 runs)``,
    ``0.021 ± 0.003 (n=3)``.  None and non-finite values are left out.  ``integer``: counts, printed
    as integers where the mean is whole (``7``), else with one decimal.
    """
    vals = [(seed, float(v) * scale) for seed, v in pairs
            if v is not None and runs.is_number(v) and math.isfinite(float(v))]
    if not vals:
        return Cell()
    by_seed = runs.group_by(vals, lambda sv: sv[0])
    means = [float(np.mean([v for _, v in svs])) for svs in by_seed.values()]
    m, k, n_runs = float(np.mean(means)), len(means), len(vals)
    text = _fmt(m, nd, integer)
    if k > 1:
        text += f" ± {_fmt(float(np.std(means, ddof=1)), nd, integer)}"
    n = f"n={k}" if n_runs == k else f"n={k} seed{'s' if k > 1 else ''}, {n_runs} runs"
    return Cell(f"{text} ({n})", m)


def seed_stat(recs: list, get, scale: float = 1.0, nd: int = 3, integer: bool = False) -> Cell:
    """:func:`stat_cell` of ``get(run)`` over runs."""
    return stat_cell([(r.seed, get(r)) for r in recs], scale, nd, integer)


def pub_cell(v) -> Cell:
    if v is None:
        return Cell()
    if isinstance(v, str):
        return Cell(v, None)
    return Cell(f"{float(v):.3f}", float(v))


def _esc_tex(s: str) -> str:
    return re.sub(r"([_%&#$])", r"\\\1", s).replace("±", r"$\pm$").replace(DASH, "--")


def write_table(t: Table, out: Path) -> list[Path]:
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["row", *t.columns, "best"])
    md = [f"### {t.title}", "", "| | " + " | ".join(t.columns) + " |", "|---" * (len(t.columns) + 1) + "|"]
    tex = [r"\begin{table}[t]", r"\centering", rf"\caption{{{_esc_tex(t.title)}}}",
           r"\begin{tabular}{l" + "c" * len(t.columns) + "}", r"\hline",
           " & " + " & ".join(_esc_tex(c) for c in t.columns) + r" \\", r"\hline"]
    for label, cells in t.rows:
        best = t.best_cols(cells)
        w.writerow([label, *[c.text for c in cells], ";".join(t.columns[i] for i in sorted(best))])
        md.append(f"| {label} | " + " | ".join(f"**{c.text}**" if i in best else c.text
                                               for i, c in enumerate(cells)) + " |")
        tex.append(_esc_tex(label) + " & " + " & ".join(rf"\textbf{{{_esc_tex(c.text)}}}" if i in best
                                                         else _esc_tex(c.text) for i, c in enumerate(cells)) + r" \\")
    tex += [r"\hline", r"\end{tabular}", r"\end{table}"]
    md += [""] + [f"{n}" for n in t.notes]
    paths = [out / f"{t.name}.csv", out / f"{t.name}.md", out / f"{t.name}.tex"]
    write_text_atomic(paths[0], buf.getvalue())
    write_text_atomic(paths[1], "\n".join(md).rstrip() + "\n")
    write_text_atomic(paths[2], "\n".join(tex) + "\n")
    return paths


# ---------------------------------------------------------------- the tables
def _defaults():
    import dynslam_cli.config  # noqa: F401
    from dynslam_cli.motion.config import MotionConfig

    return MotionConfig()


def _span(values) -> str:
    vals = sorted({v for v in values if v is not None})
    if not vals:
        return ""
    return str(vals[0]) if len(vals) == 1 else f"{vals[0]}–{vals[-1]}"


def row_label(seq: str, cut: Optional[tuple]) -> str:
    """``bonn/crowd`` for the whole sequence, ``bonn/crowd [frames 150–448 step 2]`` for a clip."""
    if cut is None:
        return seq
    start, n, stride = cut
    step = f" step {stride}" if stride > 1 else ""
    return f"{seq} [frames {start}–{start + stride * (n - 1)}{step}]" if n else f"{seq} [from frame {start}{step}]"


def frames_text(rs: list[RunRecord], cut: Optional[tuple]) -> str:
    """The frames column: ``all (1159)`` for whole-sequence runs, ``300 of 1159`` or
    ``clip of 300 frames`` (the sequence's length unknown) for a clip, '—' without runs."""
    if not rs:
        return DASH
    n = _span(r.frames for r in rs)
    if cut is None:
        return f"all ({n})" if n else "all"
    total = _span(r.total_frames for r in rs)
    n = n or "?"
    return f"{n} of {total}" if total else f"clip of {n} frames"


def grouped_rows(recs: list[RunRecord], pub_seqs=()) -> list[tuple]:
    """``[(label, frames text, runs, is_clip)]``: one row per sequence and cut.  Every sequence with
    published numbers or whole-sequence runs has its own row; each clip (start, frames, stride) of
    it gets a row of its own below, so clip values never pool with whole-sequence ones."""
    groups = runs.group_by(recs, lambda r: (r.seq, r.cut))
    keys = set(groups) | {(s, None) for s in pub_seqs}
    pub_seqs = set(pub_seqs)
    order = sorted(keys, key=lambda k: (k[0] not in pub_seqs, k[0], k[1] is not None, k[1] or ()))
    return [(row_label(*k), frames_text(groups.get(k, []), k[1]), groups.get(k, []), k[1] is not None)
            for k in order]


CLIP_NOTE = ("- frames: the frames each run processed; 'all' = the whole sequence.  Rows marked [frames a–b] "
             "are runs on a clip of the sequence: published numbers are on full sequences, so they are "
             "not shown beside clip values (compare with care; see the sequence's own row).")
SEED_NOTE = "- mean ± sample std over distinct seeds (runs with the same seed are averaged first); n = seeds."


def _pub_cells(pubsec: dict, seq: str, cols, clip: bool) -> list:
    return [Cell() if clip else pub_cell((pubsec.get(seq) or {}).get(c)) for c in cols]


def table_ate(recs: list[RunRecord], pub: dict) -> Table:
    d = _defaults()
    ours = [r for r in recs if r.mode == "static" or (r.mode == "dynamic" and r.encoder == d.encoder
                                                     and r.segmenter == d.segmenter and r.replay == d.replay
                                                     and not r.prior)]
    ate_pub = pub.get("ate") or {}
    cols = ["frames", "ours dynamic", "ours static", "still camera", *PUBLISHED_METHODS, "paper"]
    t = Table("table1_ate", "ATE RMSE (m) after SE(3) alignment; mean ± std over seeds", cols,
              best=[([1, 2, 4, 5, 6, 7, 8], True)])
    for label, frames, rs, clip in grouped_rows(ours, ate_pub):
        seq = rs[0].seq if rs else label
        row = [Cell(frames), seed_stat([r for r in rs if r.mode == "dynamic"], lambda r: r.ate),
               seed_stat([r for r in rs if r.mode == "static"], lambda r: r.ate), seed_stat(rs, lambda r: r.still)]
        row += _pub_cells(ate_pub, seq, (*PUBLISHED_METHODS, "paper"), clip)
        t.rows.append((label, row))
    srcs = pub.get("sources") or {}
    t.notes = [f"- {k}: {' '.join(str(v).split())}" for k, v in srcs.items()]
    t.notes += ["- still camera: ATE of a camera that never moves on the same matched ground truth (rmse_still_m).",
                SEED_NOTE, CLIP_NOTE]
    return t


def table_axis(recs: list[RunRecord], axis: str, pub: dict) -> Table:
    d = _defaults()
    dyn = [r for r in recs if r.mode == "dynamic"]
    if axis == "encoder":
        sel = [r for r in dyn if r.replay == d.replay and not r.prior and r.segmenter == d.segmenter]
        values = sorted({r.encoder for r in sel})
        key = lambda r: r.encoder  # noqa: E731
        labels = values
        pubsec, pubcols = pub.get("encoder_ablation") or {}, ["BLIP-2", "CLIP", "DINOv2"]
        name, title = "ablation_encoder", "ATE RMSE (m) per instance encoder (dynamic mode)"
    else:
        sel = [r for r in dyn if r.encoder == d.encoder and r.replay == d.replay and r.segmenter == d.segmenter]
        values = [False, True]
        key = lambda r: r.prior  # noqa: E731
        labels = ["without prior", "with prior"]
        pubsec, pubcols = pub.get("prior_ablation") or {}, ["without", "with"]
        name, title = "ablation_prior", "ATE RMSE (m) without / with the prior classifier"
    cols = ["frames", *labels, *[f"paper {c}" for c in pubcols]]
    t = Table(name, title, cols, best=[(list(range(1, len(labels) + 1)), True)], notes=[SEED_NOTE, CLIP_NOTE])
    for label, frames, rs, clip in grouped_rows(sel, pubsec):
        seq = rs[0].seq if rs else label
        row = [Cell(frames)] + [seed_stat([r for r in rs if key(r) == v], lambda r: r.ate) for v in values]
        row += _pub_cells(pubsec, seq, pubcols, clip)
        t.rows.append((label, row))
    return t


def table_replay(recs: list[RunRecord]) -> Table:
    d = _defaults()
    sel = [r for r in recs if r.mode == "dynamic" and r.encoder == d.encoder and not r.prior
           and r.segmenter == d.segmenter]
    cols = ["frames", "updates with replay", "updates without replay", "ATE with replay", "ATE without replay"]
    t = Table("ablation_replay", "Classifier updates and ATE RMSE (m) with / without the replay buffer", cols,
              best=[([1, 2], True), ([3, 4], True)], notes=[SEED_NOTE, CLIP_NOTE])

    def count(r):
        return len(r.updates) if r.updates is not None else None

    for label, frames, rs, _ in grouped_rows(sel):
        on, off = [r for r in rs if r.replay], [r for r in rs if not r.replay]
        row = [Cell(frames), seed_stat(on, count, integer=True), seed_stat(off, count, integer=True),
               seed_stat(on, lambda r: r.ate), seed_stat(off, lambda r: r.ate)]
        if any(c.value is not None for c in row):
            t.rows.append((label, row))
    return t


def per_call_ms(r: RunRecord, comp: str) -> Optional[float]:
    """Mean ms over the frames on which ``comp`` ran: mean per frame × frames / calls (timing.json
    ``calls``: frames with a time > 0); None when the run does not record its calls."""
    calls, frames, per_frame = r.timing_calls.get(comp), r.timing_frames, r.timing.get(comp)
    if calls is None or frames is None or per_frame is None:
        return None
    return per_frame * frames / calls if calls > 0 else None


def table_runtime(recs: list[RunRecord], pub: dict) -> Table:
    comps = sorted({k for r in recs for k in r.timing})
    pub_rt = pub.get("runtime_ms") or {}
    pub_only = [c for c in pub_rt if c not in comps]
    cols = [f"{c} {w}" for c in comps for w in ("/frame", "/call")] + pub_only + ["fps"]
    t = Table("runtime", "Mean run-time (ms) per component, per frame and per call; mean ± std over seeds", cols)
    t.notes = ["- /frame: mean over all frames (timing.json mean_ms); /call: mean over the frames on which the "
               "component ran (bundle adjustment runs every mapping.every-th frame); '—' where the run did not "
               "record its calls (timing.json calls).", SEED_NOTE]
    g = runs.group_by([r for r in recs if r.timing or r.fps is not None], lambda r: (r.seq, r.mode))
    for (s, m), rs in sorted(g.items()):
        row = []
        for c in comps:
            row += [seed_stat(rs, lambda r, c=c: r.timing.get(c), nd=1), seed_stat(rs, lambda r, c=c: per_call_ms(r, c), nd=1)]
        t.rows.append((f"{s} ({m})", row + [Cell() for _ in pub_only] + [seed_stat(rs, lambda r: r.fps, nd=2)]))
    if pub_rt:
        pub_cols = {c: Cell(f"{float(pub_rt[c]):.0f}", float(pub_rt[c])) for c in pub_rt}
        per_frame = [pub_cols.get(c.removesuffix(" /frame") if c.endswith(" /frame") else c, Cell()) for c in cols[:-1]]
        t.rows.append(("paper (Bonn, RTX 3090)", per_frame + [Cell("≈1")]))
        t.notes.append("- paper: average run-time per frame on Bonn (configs/published.yaml runtime_ms).")
    return t


def table_mesh(recs: list[RunRecord]) -> Table:
    cols = ["frames", "accuracy dyn (cm)", "accuracy static (cm)", "completion dyn (cm)", "completion static (cm)",
            "ratio dyn (%)", "ratio static (%)"]
    t = Table("mesh", "Mesh accuracy / completion (cm) and completion ratio (< 5 cm, %)", cols,
              best=[([1, 2], True), ([3, 4], True), ([5, 6], False)], notes=[SEED_NOTE, CLIP_NOTE])
    d = _defaults()
    sel = [r for r in recs if r.mesh and (r.mode == "static" or (r.mode == "dynamic" and r.encoder == d.encoder
                                                                  and not r.prior))]
    for label, frames, rs, _ in grouped_rows(sel):
        row = [Cell(frames)]
        for key, scale in (("accuracy_m", 100), ("completion_m", 100), ("completion_ratio", 100)):
            row += [seed_stat([r for r in rs if r.mode == mode], lambda r, k=key: r.mesh.get(k), scale, 2)
                    for mode in ("dynamic", "static")]
        t.rows.append((label, row))
    return t


# ---------------------------------------------------------------- entry point
@dataclass
class TablesResult:
    out: Path
    runs: int
    files: list = field(default_factory=list)
    tables: dict = field(default_factory=dict)  # name -> Table
    warnings: list = field(default_factory=list)  # one line per skipped run or file


def make_tables(results: str | Path = "results", out: Optional[str | Path] = None,
                published: Optional[str | Path] = None, plots: bool = True,
                include_incomplete: bool = False) -> TablesResult:
    """Tables (and plots) from the run folders under ``results``.  Runs that are not completed
    (unless ``include_incomplete``) and unusable files are skipped, each with a line in
    ``warnings``; the others still make the tables."""
    results = Path(results)
    out = Path(out) if out is not None else results / "tables"
    warnings: list[str] = []
    recs = collect_runs(results, warnings, include_incomplete)
    pub = load_published(Path(published) if published else None)
    tables = [table_ate(recs, pub), table_axis(recs, "encoder", pub), table_axis(recs, "prior", pub),
              table_replay(recs), table_runtime(recs, pub), table_mesh(recs)]
    files: list[Path] = []
    for t in tables:
        files += write_table(t, out)
    plot_files: list[Path] = []
    if plots:
        plot_files += plot_updates(recs, out)
        for r in recs:
            rel = r.path.relative_to(results)
            try:
                p = montage(r.path, out / "plots" / f"montage_{'__'.join(rel.parts)}.png")
            except DynslamError as exc:
                warnings.append(f"no montage of run {r.path}: {exc}")
                continue
            if p is not None:
                plot_files.append(p)
    ate_pngs = [r.path / "ate.png" for r in recs if (r.path / "ate.png").is_file()]
    what = "runs (completed or not)" if include_incomplete else "completed runs"
    index = ["# Tables", "", f"{len(recs)} {what} read from `{results}`; {len(warnings)} warnings.", ""]
    index += [f"- [{t.title}]({t.name}.md)" for t in tables]
    index += ["", "## Plots", ""] + [f"- {p.relative_to(out)}" for p in plot_files]
    index += ["", "## Trajectory plots (ate.png, written by eval-ate)", ""] + [f"- {p}" for p in ate_pngs]
    if warnings:
        index += ["", "## Skipped", ""] + [f"- {w}" for w in warnings]
    files.append(write_text_atomic(out / "README.md", "\n".join(index) + "\n"))
    return TablesResult(out, len(recs), files + plot_files, {t.name: t for t in tables}, warnings)
