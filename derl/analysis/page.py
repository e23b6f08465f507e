"""The report's HTML page: the headline numbers (each run's first and last quarter of births
compared), the figures beside it with their captions, the best bodies' gaits, the run and world
summaries, links to the tables and the notes (what was sampled, counted once, censored, what had
too little data). One file, no scripts, no external resources; the PNGs and GIFs are referenced
by relative path.
"""

from __future__ import annotations

from html import escape
from pathlib import Path

from derl.analysis.compute import RunSummary, WorldSummary
from derl.analysis.records import Record

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1200px; margin: 2em auto; color: #222; }
figure { margin: 2em 0; } img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; max-width: 900px; }
table { border-collapse: collapse; font-size: 0.85em; }
td, th { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
.notes li { font-size: 0.9em; }
figure.gait { display: inline-block; margin: 0.5em; vertical-align: top; }
"""

SUMMARY_COLUMNS = {
    "run": "run",
    "world": "world",
    "bodies": "births",
    "distinct_bodies": "bodies",
    "repeats": "repeats (counted once)",
    "population": "P",
    "generations": "generations",
    "surviving_lineages": "surviving lineages",
    "beneficial_threshold": "beneficial threshold",
    "beneficial_mutations": "beneficial mutations",
    "gain_p75": "p75 of positive gains",
    "criterion": "learning criterion",
    "criterion_censored": "never reached it (censored)",
    "no_positive_reward": "no positive reward (censored cost of work)",
    "stability_simulated": "stability simulated",
    "fingerprint": "fingerprint",
    "audited": "audited births",
    "quarantined": "quarantined trainers",
}


QUARTER_COLUMNS = {
    "run": "run",
    "births": "births per quarter",
    "first": "first quarter: median fitness",
    "last": "last quarter: median fitness",
    "difference": "difference (last - first)",
    "low": "CI low",
    "high": "CI high",
    "first_bodies": "distinct bodies in the first",
    "last_bodies": "distinct bodies in the last",
    "first_lineages": "their lineages in the first",
    "last_lineages": "their lineages in the last",
}


WORLD_COLUMNS = {
    "world": "world",
    "runs": "runs",
    "top_rule": "top agents chosen by",
    "top_agents": "top agents (n)",
    "retrained_bodies": "retrained bodies",
    "partially_retrained": "not every seed (not ranked)",
    "retrainings": "retrainings",
    "retrainings_repeated": "repeated retrainings left out",
    "shared_bodies": "bodies of several runs (counted once)",
    "top_of_population": "fig. 2a left n",
    "births": "pooled up to birth",
}


class FigureEntry(Record):
    """A figure on the page: its file (beside the page), title and caption."""

    file: str
    title: str
    caption: str


class Gait(Record):
    """A best body's gait on the page: its clip (a GIF beside the page) and who it is."""

    file: str
    label: str


GAITS_TITLE = "The best bodies' gaits"


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, list | tuple):
        return escape(", ".join(map(str, value))) or "none"
    return f"{value:.4g}" if isinstance(value, float) else escape(str(value))


def _table(rows: list[dict[str, object]], columns: dict[str, str]) -> str:
    """`rows` as an HTML table of the given fields, headed by their names."""
    header = "".join(f"<th>{escape(name)}</th>" for name in columns.values())
    cells = "".join(
        "<tr>" + "".join(f"<td>{_cell(row[key])}</td>" for key in columns) + "</tr>" for row in rows
    )
    return f"<table><tr>{header}</tr>{cells}</table>"


def _quarters(summaries: list[RunSummary]) -> list[dict[str, object]]:
    """Each run's first and last quarter of births compared (each body once, the interval
    resampling lineages), as rows of `QUARTER_COLUMNS`."""
    return [
        {
            "run": s.run,
            "births": q.births,
            "first": q.first.value,
            "last": q.last.value,
            "difference": q.difference.value,
            "low": q.difference.low,
            "high": q.difference.high,
            "first_bodies": q.first.n,
            "last_bodies": q.last.n,
            "first_lineages": q.first_lineages,
            "last_lineages": q.last_lineages,
        }
        for s in summaries
        if (q := s.quarters) is not None
    ]


def _gaits(gaits: list[Gait]) -> list[str]:
    """The gaits' section, side by side (none without gaits)."""
    if not gaits:
        return []
    clips = (
        f'<figure class="gait"><img src="{escape(g.file)}" alt="{escape(g.label)}">'
        f"<figcaption>{escape(g.label)}</figcaption></figure>"
        for g in gaits
    )
    return [
        f'<section id="gaits"><h2>{escape(GAITS_TITLE)}</h2>',
        *clips,
        "<p>Each body's trained policy (its mean actions) replayed from its checkpoint in its "
        "run's world: the first episode, at half speed; run/id: fitness.</p></section>",
    ]


def write_page(
    path: Path,
    title: str,
    headline: list[str],
    figures: list[FigureEntry],
    summaries: list[RunSummary],
    worlds: list[WorldSummary],
    tables: list[Path],
    notes: list[str],
    gaits: list[Gait],
) -> Path:
    body = [
        f"<h1>{escape(title)}</h1>",
        "<ul>",
        *(f"<li>{escape(line)}</li>" for line in headline),
        "</ul>",
        "<h2>Evolution's progress: the first and the last quarter of births</h2>",
        _table(_quarters(summaries), QUARTER_COLUMNS),
        "<h2>Runs</h2>",
        _table([dict(s) for s in summaries], SUMMARY_COLUMNS),
        "<h2>Worlds (runs pooled)</h2>",
        _table([dict(w) for w in worlds], WORLD_COLUMNS),
        "<h2>Tables</h2><ul>",
        *(f'<li><a href="{escape(t.name)}">{escape(t.name)}</a></li>' for t in tables),
        "</ul>",
        '<h2>Notes</h2><ul class="notes">',
        *(f"<li>{escape(note)}</li>" for note in notes),
        "</ul>",
        *(
            f'<figure id="{escape(Path(f.file).stem)}"><h2>{escape(f.title)}</h2>'
            f'<img src="{escape(f.file)}" alt="{escape(f.title)}">'
            f"<figcaption>{escape(f.caption)}</figcaption></figure>"
            for f in figures
        ),
        *_gaits(gaits),
    ]
    path.write_text(
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
        f"<title>{escape(title)}</title><style>{STYLE}</style></head>\n<body>\n"
        + "\n".join(body)
        + "\n</body></html>\n"
    )
    return path
