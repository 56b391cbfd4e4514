"""`dynslam tables`: paper-style tables and plots from result files only.

Reads every run folder (a folder holding ``run.json``) under the results folder -- plain runs
(``runs/<dataset>/<sequence>/<variant>/``) and ablation cells (``ablations/<name>/<cell>/``) --
and writes ``<out>/<table>.{csv,md,tex}`` plus ``<out>/plots/*.png`` and ``<out>/README.md``.

Files read per run: run.json (status, sequence.dataset/name, mode, seed), config.yaml (motion
settings: encoder, segmenter, replay, prior), ate.json, mesh_metrics.json, timing.json
(``median_ms``, ``fps``), classifier_updates.jsonl (one line per update; its ``frame``/``index``/
``timestamp`` field, else the line number, places it in time), masks/<ts>.png and, when
present, renders/<ts>_depth.png and the input rgb/<ts>.png of the sequence (montage).

Only runs with status ``completed`` count.  Values are mean ± sample std over seeds (the std
is left out for a single seed); '—' where nothing exists.  The best value of a row is bold in
Markdown/LaTeX and named in the CSV's ``best`` column.  Which runs feed which table:

* Table 1 (ATE): "ours dynamic" pools dynamic runs at the default motion settings (encoder,
  segmenter and replay as the config defaults, no prior); "ours static" pools static runs;
  "still camera" is ``rmse_still_m`` of those runs (see eval/ate.py); the published columns come
  from configs/published.yaml.  The best of a row is taken over the method columns (not still).
* Encoder / prior / replay ablations: each varies one axis and pools the dynamic runs whose other
  motion axes are at their defaults.
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
    timing: dict = field(default_factory=dict)
    fps: Optional[float] = None
    updates: Optional[list] = None  # positions in time of each classifier update


def _read_opt_json(path: Path):
    return runs.read_json(path, path.name) if path.is_file() else None


def _updates(path: Path) -> Optional[list]:
    if not path.is_file():
        return None
    out = []
    for i, line in enumerate(path.read_text().splitlines()):
        if not line.strip():
            continue
        try:
            d = json.loads(line)
        except json.JSONDecodeError:
            raise DynslamError(f"corrupt classifier_updates.jsonl {path} line {i + 1}") from None
        pos = i
        if isinstance(d, dict):
            for k in ("frame", "index", "timestamp"):
                if isinstance(d.get(k), (int, float)):
                    pos = d[k]
                    break
        out.append(pos)
    return out


def read_run(run_dir: Path) -> Optional[RunRecord]:
    import dynslam_cli.config  # noqa: F401 - the config package first (avoids a circular import)
    from dynslam_cli.motion.config import MotionConfig

    meta = runs.read_run_json(run_dir, required=True)
    if meta.get("status") != "completed":
        return None
    seq = runs.sequence_info(run_dir, meta)
    key = f"{seq.get('dataset', '?')}/{seq.get('name', run_dir.name)}"
    motion = (runs.read_run_config(run_dir).get("motion") or {})
    dm = MotionConfig()
    cfg_run = runs.read_run_config(run_dir).get("run") or {}
    rec = RunRecord(
        path=run_dir, seq=key, mode=str(meta.get("mode") or cfg_run.get("mode") or "dynamic"),
        seed=int(meta.get("seed", cfg_run.get("seed", 0)) or 0),
        encoder=str(motion.get("encoder", dm.encoder)), segmenter=str(motion.get("segmenter", dm.segmenter)),
        replay=bool(motion.get("replay", dm.replay)), prior=bool(motion.get("prior", dm.prior)),
    )
    ate = _read_opt_json(run_dir / "ate.json")
    if ate:
        rec.ate, rec.still = ate.get("rmse_m"), ate.get("rmse_still_m")
    rec.mesh = _read_opt_json(run_dir / "mesh_metrics.json") or {}
    timing = _read_opt_json(run_dir / "timing.json") or {}
    rec.timing = dict(timing.get("median_ms") or {})
    rec.fps = timing.get("fps")
    rec.updates = _updates(run_dir / "classifier_updates.jsonl")
    return rec


def collect_runs(results: Path) -> list[RunRecord]:
    if not results.is_dir():
        raise DynslamError(f"results folder not found: {results}")
    recs = []
    for rj in sorted(results.rglob("run.json")):
        if "tables" in rj.relative_to(results).parts[:1]:
            continue
        r = read_run(rj.parent)
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


def stat_cell(values: list, scale: float = 1.0, nd: int = 3) -> Cell:
    vals = [float(v) * scale for v in values if v is not None and math.isfinite(float(v))]
    if not vals:
        return Cell()
    m = float(np.mean(vals))
    if len(vals) == 1:
        return Cell(f"{m:.{nd}f}", m)
    return Cell(f"{m:.{nd}f} ± {float(np.std(vals, ddof=1)):.{nd}f}", m)


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


def table_ate(recs: list[RunRecord], pub: dict) -> Table:
    d = _defaults()
    dyn = [r for r in recs if r.mode == "dynamic" and r.encoder == d.encoder and r.segmenter == d.segmenter
           and r.replay == d.replay and not r.prior]
    sta = [r for r in recs if r.mode == "static"]
    ate_pub = pub.get("ate") or {}
    seqs = sorted(set(ate_pub) | {r.seq for r in dyn + sta}, key=lambda s: (s not in ate_pub, s))
    cols = ["ours dynamic", "ours static", "still camera", *PUBLISHED_METHODS, "paper"]
    t = Table("table1_ate", "ATE RMSE (m) after SE(3) alignment; mean ± std over seeds", cols,
              best=[([0, 1, 3, 4, 5, 6, 7], True)])
    gd, gs = runs.group_by(dyn, lambda r: r.seq), runs.group_by(sta, lambda r: r.seq)
    for s in seqs:
        ours = gd.get(s, []) + gs.get(s, [])
        row = [stat_cell([r.ate for r in gd.get(s, [])]), stat_cell([r.ate for r in gs.get(s, [])]),
               stat_cell([r.still for r in ours])]
        row += [pub_cell((ate_pub.get(s) or {}).get(m)) for m in (*PUBLISHED_METHODS, "paper")]
        t.rows.append((s, row))
    srcs = pub.get("sources") or {}
    t.notes = [f"- {k}: {' '.join(str(v).split())}" for k, v in srcs.items()]
    t.notes.append("- still camera: ATE of a camera that never moves on the same matched ground truth (rmse_still_m).")
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
    seqs = sorted({r.seq for r in sel} | set(pubsec))
    cols = [*labels, *[f"paper {c}" for c in pubcols]]
    t = Table(name, title, cols, best=[(list(range(len(labels))), True)])
    g = runs.group_by(sel, lambda r: (r.seq, key(r)))
    for s in seqs:
        row = [stat_cell([r.ate for r in g.get((s, v), [])]) for v in values]
        row += [pub_cell((pubsec.get(s) or {}).get(c)) for c in pubcols]
        t.rows.append((s, row))
    return t


def table_replay(recs: list[RunRecord]) -> Table:
    d = _defaults()
    sel = [r for r in recs if r.mode == "dynamic" and r.encoder == d.encoder and not r.prior
           and r.segmenter == d.segmenter]
    cols = ["updates with replay", "updates without replay", "ATE with replay", "ATE without replay"]
    t = Table("ablation_replay", "Classifier updates and ATE RMSE (m) with / without the replay buffer", cols,
              best=[([0, 1], True), ([2, 3], True)])
    g = runs.group_by(sel, lambda r: (r.seq, r.replay))
    for s in sorted({r.seq for r in sel}):
        on, off = g.get((s, True), []), g.get((s, False), [])
        row = [stat_cell([len(r.updates) if r.updates is not None else None for r in on], nd=1),
               stat_cell([len(r.updates) if r.updates is not None else None for r in off], nd=1),
               stat_cell([r.ate for r in on]), stat_cell([r.ate for r in off])]
        if any(c.value is not None for c in row):
            t.rows.append((s, row))
    return t


def table_runtime(recs: list[RunRecord], pub: dict) -> Table:
    comps = sorted({k for r in recs for k in r.timing})
    pub_rt = pub.get("runtime_ms") or {}
    comps = comps + [c for c in pub_rt if c not in comps]
    t = Table("runtime", "Median run-time per frame and component (ms); mean ± std over seeds", [*comps, "fps"])
    g = runs.group_by([r for r in recs if r.timing or r.fps], lambda r: (r.seq, r.mode))
    for (s, m), rs in sorted(g.items()):
        t.rows.append((f"{s} ({m})", [stat_cell([r.timing.get(c) for r in rs], nd=1) for c in comps]
                       + [stat_cell([r.fps for r in rs], nd=2)]))
    if pub_rt:
        t.rows.append(("paper (Bonn, RTX 3090)", [Cell(f"{float(pub_rt[c]):.0f}", float(pub_rt[c])) if c in pub_rt
                                                  else Cell() for c in comps] + [Cell("≈1")]))
    return t


def table_mesh(recs: list[RunRecord]) -> Table:
    cols = ["accuracy dyn (cm)", "accuracy static (cm)", "completion dyn (cm)", "completion static (cm)",
            "ratio dyn (%)", "ratio static (%)"]
    t = Table("mesh", "Mesh accuracy / completion (cm) and completion ratio (< 5 cm, %)", cols,
              best=[([0, 1], True), ([2, 3], True), ([4, 5], False)])
    d = _defaults()
    dyn = [r for r in recs if r.mode == "dynamic" and r.mesh and r.encoder == d.encoder and not r.prior]
    sta = [r for r in recs if r.mode == "static" and r.mesh]
    gd, gs = runs.group_by(dyn, lambda r: r.seq), runs.group_by(sta, lambda r: r.seq)
    for s in sorted(set(gd) | set(gs)):
        row = []
        for key, scale in (("accuracy_m", 100), ("completion_m", 100), ("completion_ratio", 100)):
            row += [stat_cell([r.mesh.get(key) for r in gd.get(s, [])], scale, 2),
                    stat_cell([r.mesh.get(key) for r in gs.get(s, [])], scale, 2)]
        t.rows.append((s, row))
    return t


# ---------------------------------------------------------------- entry point
@dataclass
class TablesResult:
    out: Path
    runs: int
    files: list = field(default_factory=list)
    tables: dict = field(default_factory=dict)  # name -> Table


def make_tables(results: str | Path = "results", out: Optional[str | Path] = None,
                published: Optional[str | Path] = None, plots: bool = True) -> TablesResult:
    results = Path(results)
    out = Path(out) if out is not None else results / "tables"
    recs = collect_runs(results)
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
            p = montage(r.path, out / "plots" / f"montage_{'__'.join(rel.parts)}.png")
            if p is not None:
                plot_files.append(p)
    ate_pngs = [r.path / "ate.png" for r in recs if (r.path / "ate.png").is_file()]
    index = ["# Tables", "", f"{len(recs)} completed runs read from `{results}`.", ""]
    index += [f"- [{t.title}]({t.name}.md)" for t in tables]
    index += ["", "## Plots", ""] + [f"- {p.relative_to(out)}" for p in plot_files]
    index += ["", "## Trajectory plots (ate.png, written by eval-ate)", ""] + [f"- {p}" for p in ate_pngs]
    files.append(write_text_atomic(out / "README.md", "\n".join(index) + "\n"))
    return TablesResult(out, len(recs), files + plot_files, {t.name: t for t in tables})
