"""The paper's Tab. I-IV as ``gtgen experiments`` fills them: each table's columns
(``Metric``: where a value lies in an evaluation), rows (``Line``: the runs it needs and
the paper's numbers) and their text (``cell_texts``, ``markdown``). Which runs are trained
and how: ``gtgen.train.experiments``.
"""

from __future__ import annotations

from dataclasses import dataclass

from gtgen.config import RANGES
from gtgen.errors import ConfigError
from gtgen.report.stats import PAPER_REGION_SHARE_PCT, PAPER_XRACER_AT_T
from gtgen.runtime.output import signature

TABLES = ("I", "II", "III", "IV")
REGIONS = ("obs_pc", "obs_f", "unobs", "total")
REGION_NAMES = {"obs_pc": "obs PC", "obs_f": "obs F", "unobs": "unobs", "total": "Total"}


@dataclass(frozen=True)
class Metric:
    """A column: ``kind`` mae (elevation MAE of region ``key``), risk (``key``: mse, precision,
    recall, f1) or cons (the consistency MAE), of range ``rng``."""

    header: str
    rng: str
    kind: str
    key: str = ""
    digits: int = 3

    def path(self, method: str) -> tuple[str, ...]:
        """Return the path of the value in an evaluation result (``method``: its row; "share":
        the region's share of the labelled cells)."""
        if self.kind == "cons":
            return ("consistency_mae_m",)
        if self.kind == "risk":
            return ("risk", self.rng, method, self.key)
        if method == "share":
            return ("elevation", self.rng, "model", self.key, "share_pct")
        return ("elevation", self.rng, method, self.key, "mae_m")


@dataclass(frozen=True)
class Line:
    """A table row: the runs it needs (the one giving a column is the one predicting its
    range), the evaluation row it reads (``method``: model, or a baseline row of the Ours run
    such as xracer), and the paper's numbers per column (None: not in the paper)."""

    label: str
    inputs: str
    runs: tuple[str, ...]
    paper: tuple[float | None, ...]
    method: str = "model"
    paper_coverage: tuple[float | None, ...] = ()


@dataclass(frozen=True)
class Table:
    number: str
    title: str
    metrics: tuple[Metric, ...]
    lines: tuple[Line, ...]


def _per_range(stem: str) -> tuple[str, ...]:
    return tuple(f"{stem}-{r}" for r in RANGES)


def _xracer_tab1(r: str, key: str) -> tuple[float | None, ...]:
    """Return the paper's X-Racer-at-t Tab. I columns (obs PC, obs F, unobs, total) of ``key``."""
    return (*PAPER_XRACER_AT_T[r][key].values(), None)


def _xracer_tab2(r: str) -> tuple[float | None, ...]:
    """Return the paper's X-Racer-at-t Tab. II columns (MSE, precision, recall, F1)."""
    return tuple(PAPER_XRACER_AT_T[r]["risk"][k] for k in ("mse", "precision", "recall", "f1"))


# the paper's numbers (Tab. I-IV); Tab. I's share row is each region's share of the labelled cells [%]
_TAB1 = {
    "micro": {"share": (*PAPER_REGION_SHARE_PCT["micro"].values(), None), "lss": (0.819, 1.01, 2.093, 1.167), "pp": (0.41, 0.545, 1.208, 0.635),
              "xracer": _xracer_tab1("micro", "mae_m"), "xracer_cov": _xracer_tab1("micro", "coverage_pct"), "rr": (0.399, 0.592, 1.629, 0.738),
              "womr": (0.241, 0.422, 1.261, 0.532), "ours": (0.215, 0.318, 0.869, 0.396)},
    "short": {"share": (*PAPER_REGION_SHARE_PCT["short"].values(), None), "lss": (1.489, 1.948, 3.606, 2.638), "pp": (0.732, 0.868, 1.992, 1.368),
              "xracer": _xracer_tab1("short", "mae_m"), "xracer_cov": _xracer_tab1("short", "coverage_pct"), "rr": (0.418, 0.852, 2.311, 1.453),
              "womr": (0.276, 0.627, 1.835, 1.126), "ours": (0.288, 0.65, 1.874, 1.155)},
}
_TAB2 = {  # MSE, precision, recall, F1 (the paper's X-Racer F1 is as printed there)
    "micro": {"lss": (0.0104, 0.363, 0.113, 0.173), "pp": (0.0086, 0.466, 0.189, 0.269), "xracer": _xracer_tab2("micro"),
              "xracer_cov": (None, PAPER_XRACER_AT_T["micro"]["risk"]["coverage_pct"], None, None), "rr": (0.0086, 0.501, 0.207, 0.293), "womr": (0.0080, 0.519, 0.240, 0.329),
              "ours": (0.0076, 0.523, 0.272, 0.357)},
    "short": {"lss": (0.0237, 0.241, 0.241, 0.241), "pp": (0.0173, 0.431, 0.291, 0.347), "xracer": _xracer_tab2("short"),
              "xracer_cov": (None, PAPER_XRACER_AT_T["short"]["risk"]["coverage_pct"], None, None), "rr": (0.0175, 0.433, 0.305, 0.358), "womr": (0.0165, 0.473, 0.343, 0.397),
              "ours": (0.0166, 0.465, 0.345, 0.396)},
}
_TAB3 = {1: (0.592, 0.304, 1.563, 0.331), 2: (0.521, 0.307, 1.372, 0.350), 5: (0.466, 0.316, 1.299, 0.358),
         10: (0.438, 0.331, 1.115, 0.375), "VM": (0.403, 0.358, 1.136, 0.394)}
_TAB4 = {"UL": (0.229, 0.333, 0.853, 0.298, 0.655, 1.849, 0.18), "CL": (0.216, 0.347, 1.246, 0.278, 1.025, 3.575, 0.08),
         "UL + CL": (0.215, 0.319, 0.870, 0.289, 0.650, 1.874, 0.09)}


def paper_tables(lidar: str, cameras: bool = True) -> list[Table]:
    """Return the paper's tables; ``lidar`` names the "L" input of this dataset, and without
    ``cameras`` the rows' inputs go without "C" (the runs' camera input is off)."""
    if not cameras:
        return [_without_cameras(t) for t in paper_tables(lidar)]
    out = []
    for r in RANGES:
        p = _TAB1[r]
        out.append(Table("I", f"Tab. I, {r} range: elevation MAE [m] (in brackets: coverage of the labelled cells)",
                         tuple(Metric(REGION_NAMES[k], r, "mae", k) for k in REGIONS), (
            Line("share of the labelled cells [%]", "", ("ours",), p["share"], "share"),
            Line("LSS", "C", _per_range("lss"), p["lss"]),
            Line("PointPillars", lidar, _per_range("pp"), p["pp"]),
            Line("X-Racer at t", "C + VM", ("ours",), p["xracer"], "xracer", p["xracer_cov"]),
            Line("raw min z, nearest-filled", "VM", ("ours",), (None,) * 4, "raw_nearest"),
            Line("RoadRunner", "C + L + E", _per_range("rr"), p["rr"]),
            Line("Ours w/o MR", "C + VM", _per_range("ours"), p["womr"]),
            Line("Ours", "C + VM", ("ours",), p["ours"]))))
    for r in RANGES:
        p = _TAB2[r]
        out.append(Table("II", f"Tab. II, {r} range: risk (fatal: risk >= train.fatal_risk)",
                         tuple(Metric(h, r, "risk", k, 4 if k == "mse" else 3) for h, k in
                               (("MSE", "mse"), ("Precision", "precision"), ("Recall", "recall"), ("F1", "f1"))), (
            Line("LSS", "C", _per_range("lss"), p["lss"]),
            Line("PointPillars", lidar, _per_range("pp"), p["pp"]),
            Line("X-Racer at t", "C + VM", ("ours",), p["xracer"], "xracer", p["xracer_cov"]),
            Line("RoadRunner", "C + L + E", _per_range("rr"), p["rr"]),
            Line("Ours w/o MR", "C + VM", _per_range("ours"), p["womr"]),
            Line("Ours", "C + VM", ("ours",), p["ours"]))))
    out.append(Table("III", "Tab. III: point cloud accumulation (elevation MAE [m] over all labelled cells, risk F1)",
                     (Metric("micro MAE", "micro", "mae", "total"), Metric("micro F1", "micro", "risk", "f1"),
                      Metric("short MAE", "short", "mae", "total"), Metric("short F1", "short", "risk", "f1")),
                     tuple(Line(f"N={n}", "C + N scans", (f"scans-{n}",), _TAB3[n]) for n in (1, 2, 5, 10))
                     + (Line("VM", "C + VM (= Ours)", ("ours",), _TAB3["VM"]),)))
    out.append(Table("IV", "Tab. IV: the loss (UL: unobserved loss, CL: consistency loss); elevation MAE [m]",
                     tuple(Metric(f"{r} {REGION_NAMES[k]}", r, "mae", k) for r in RANGES for k in REGIONS[:3])
                     + (Metric("Cons. MAE", "micro", "cons"),),
                     (Line("UL", "gamma = 0", ("ul",), _TAB4["UL"]), Line("CL", "alpha = 0", ("cl",), _TAB4["CL"]),
                      Line("UL + CL", "= Ours", ("ours",), _TAB4["UL + CL"]))))
    return out


def _without_cameras(t: Table) -> Table:
    """Return table ``t`` with its trained rows' inputs named without the cameras ("C + ")."""
    lines = tuple(ln if ln.method != "model" else Line(ln.label, ln.inputs.removeprefix("C + "), ln.runs, ln.paper, ln.method,
                                                       ln.paper_coverage) for ln in t.lines)
    return Table(t.number, t.title, t.metrics, lines)


def parse_tables(text: str) -> tuple[str, ...]:
    """Return the table numbers of ``--tables`` ('I,III,IV'), in the paper's order."""
    asked = [t.strip().upper() for t in text.split(",") if t.strip()]
    bad = [t for t in asked if t not in TABLES]
    if bad or not asked:
        raise ConfigError(f"--tables {text!r}: expected a comma-separated list of {', '.join(TABLES)}")
    return tuple(t for t in TABLES if t in asked)


def table_value(res: dict, m: Metric, method: str, seeds: int) -> dict:
    """Return the mean, spread (None for one seed) and coverage [%] of metric ``m`` of row
    ``method`` in a reduced evaluation."""
    node, sp = res, res["spread"]
    path = m.path(method)
    for k in path:
        node, sp = node[k], (sp[k] if sp is not None else None)
    cov = None
    if m.kind != "cons" and method != "share":
        tab = res["elevation" if m.kind == "mae" else "risk"][m.rng][method]
        cov = (tab[m.key] if m.kind == "mae" else tab)["coverage_pct"]
    return {"mean": node, "spread": sp if seeds > 1 else None, "coverage_pct": cov}


def _number(v: float | None, digits: int, pct: bool = False) -> str:
    if v is None:
        return "—"
    return f"{v:.1f} %" if pct else f"{v:.{digits}f}"


def cell_texts(table: dict) -> tuple[list[str], list[list[str]]]:
    """Return the header and the rows of a filled table as text: Method, Input, then per
    column ours (mean ± spread, coverage when partial) and the paper's."""
    head = ["Method", "Input"] + [h for c in table["columns"] for h in (c, "paper")]
    rows = []
    for row in table["rows"]:
        pct = row["method"] == "share"
        texts = [row["label"], row["inputs"]]
        for c, digits in zip(row["cells"], table["digits"]):
            ours = _number(c["mean"], digits, pct)
            # none for one seed; 0 (to float rounding) for what every seed shares: baselines, shares
            if c["spread"] is not None and c["mean"] is not None and c["spread"] > 1e-6 * abs(c["mean"]):
                ours += f" ± {_number(c['spread'], digits, pct)}"
            if c["coverage_pct"] is not None and c["mean"] is not None and c["coverage_pct"] < 99.95:
                ours += f" ({c['coverage_pct']:.0f} %)"
            paper = _number(c["paper"], digits, pct)
            if c["paper_coverage_pct"] is not None:
                paper += f" ({c['paper_coverage_pct']:.0f} %)"
            texts += [ours, paper]
        rows.append(texts)
    return head, rows


def markdown(tables: list[dict], summary: dict) -> str:
    """Return the tables as Markdown, with what they were computed on."""
    lines = [f"<!-- {signature()} -->", "# The paper's experiments on this dataset", "",
             f"Dataset `{summary['dataset']}`, evaluated on its {summary['split']} split; preset {summary['preset']}, "
             f"{summary['steps']} steps per run, {summary['seeds']} seed(s) (ours: mean ± spread over the seeds, "
             "no spread where every seed gives the same: the baselines, the shares; paper: the paper's numbers).", ""]
    lines += [f"- {n}" for n in summary["notes"]] + ([""] if summary["notes"] else [])
    for t in tables:
        head, rows = cell_texts(t)
        lines += [f"## {t['title']}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows] + [""]
    return "\n".join(lines)
