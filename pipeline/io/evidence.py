"""Evidence a person can read: one picture per match, one summary per scan.

The picture shows the suspect registered onto the original (left) and the
original's watermark clusters coloured by how strongly the accused
recipient's fingerprint was found in each (right), in the original's two
principal directions.  The summary (Markdown) lists every suspect with its
verdict, how sure, and against which issued copy.
"""

from __future__ import annotations

import io
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .pointcloud import atomic_write_bytes

__all__ = ["render_match", "write_summary", "md_cell", "plain_text"]

_MAX_POINTS = 20000
_CONTROL = {c: f"\\x{c:02x}" if c < 256 else f"\\u{c:04x}" for c in [*range(32), *range(127, 160), 0x2028, 0x2029]}


def plain_text(text, limit=400):
    """One line of at most ``limit`` characters: control characters (newlines too) as ``\\xNN``.

    For file names and error text that go into the scan's results: a name or
    a file's content can carry newlines, which must not start a line of their own.
    """
    text = str(text).translate(_CONTROL)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def md_cell(text, limit=400):
    """``text`` as one Markdown table cell: one line (:func:`plain_text`), pipes, backticks and markup escaped.

    A suspect's file name or an error quoting a file's first line can hold
    ``|`` and newlines; unescaped they would add rows (a forged accusation)
    to the report.
    """
    text = plain_text(text, limit)
    for ch in "\\`|*_[]<>#":
        text = text.replace(ch, "\\" + ch)
    return text


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _view(points, centre, axes):
    return (points - centre) @ axes[:, :2]


def render_match(original, suspect, registration, clusters, cluster_scores, title, path):
    """Write the evidence picture of one match (PNG).

    Parameters
    ----------
    original : (n, 3) float
    suspect : (m, 3) float, as found
    registration : dict
        ``rotation`` (3x3), ``scale``, ``translation`` mapping the centred
        suspect onto the centred original, ``centre`` (3,) of the original frame.
    clusters : list of (n_c,) int
        Members of the original's clusters.
    cluster_scores : (k,) float
    title : str
    path : str or Path

    Returns
    -------
    pathlib.Path
    """
    plt = _plt()
    centre = np.asarray(registration["centre"])
    rotation = np.asarray(registration["rotation"])
    aligned = registration["scale"] * (suspect - centre) @ rotation.T + np.asarray(registration["translation"]) + centre
    _, _, vt = np.linalg.svd(original[:: max(1, len(original) // 5000)] - original.mean(axis=0), full_matrices=False)
    axes = vt.T
    rng = np.random.default_rng(0)
    o_idx = rng.permutation(len(original))[:_MAX_POINTS]
    s_idx = rng.permutation(len(aligned))[:_MAX_POINTS]
    o2, s2 = _view(original, centre, axes), _view(aligned, centre, axes)
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 6.2))
    left.scatter(*o2[o_idx].T, s=1, c="0.75", label="original (issued asset)")
    left.scatter(*s2[s_idx].T, s=1, c="tab:red", alpha=0.6, label="suspect, registered")
    left.set_title(f"suspect on the original (fitness {registration.get('fitness', float('nan')):.2f}, "
                   f"scale {registration['scale']:.3g})", fontsize=10)
    left.legend(loc="upper right", markerscale=8, fontsize=9)
    right.scatter(*o2[o_idx].T, s=1, c="0.85")
    scores = np.asarray(cluster_scores, dtype=np.float64)
    top = max(float(np.abs(scores).max()), 1.0)
    cmap = plt.get_cmap("RdYlGn")
    for c, members in enumerate(clusters):
        pts = o2[members[rng.permutation(len(members))[:4000]]]
        right.scatter(*pts.T, s=2, color=cmap(0.5 + 0.5 * scores[c] / top))
        right.annotate(f"cluster {c}\nscore {scores[c]:.1f}", pts.mean(axis=0), fontsize=9, ha="center",
                       bbox={"boxstyle": "round", "fc": "white", "alpha": 0.8})
    right.set_title("where the fingerprint was found (green: strong, red: against)", fontsize=10)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(-top, top))
    fig.colorbar(sm, ax=right, label="cluster score (fingerprint correlation)")
    for ax in (left, right):
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    # a file name is text, never mathtext: "$\\x$" in a suspect's name would stop the drawing
    fig.suptitle(plain_text(title, 300).replace("$", r"\$"), fontsize=11)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


def write_summary(rows, path, epsilon, notices=()):
    """Write the scan summary (Markdown) from its result rows; returns its path.

    ``notices``: lines said above the table (ledger rows set aside, copies
    under keys not held), escaped like every cell.
    """
    import json

    latest = {}
    for r in sorted(rows, key=lambda r: (r.get("scanned_at") is None, r.get("scanned_at"))):
        latest[r["suspect_path"]] = r        # one row per file: the same bytes at two paths are two suspects
    rows = sorted(latest.values(), key=lambda r: ({"match": 0, "inconclusive": 1, "failed": 2}.get(r["verdict"], 3),
                                                  r["suspect_path"]))
    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("match", "inconclusive", "no match", "failed")}
    lines = ["# pointmark leak scan", "",
             f"Written {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC. {len(rows)} suspect files: "
             + ", ".join(f"{n} {v}" for v, n in counts.items()) + ".", "",
             "How to read it. Every issued copy carries its own secret fingerprint. A recipient is named only "
             "when the suspect's score for that recipient clears a threshold set so that the probability of "
             f"naming any innocent recipient is at most {epsilon:g} per suspect, counting every recipient of every "
             "asset, key and generation the suspect was checked against. The p-value is that bound for the "
             "score found (smaller is surer); the margin is how far the score stands above the best score of "
             "anyone not named. 'Inconclusive' means a fingerprint is present but no one clears the threshold; "
             "'failed' means the check could not be done (it is retried by the next scan). 'Registration failed' "
             "means the suspect could not be laid onto any candidate asset (under 5 % of it on the asset, or "
             "under 10 % of the asset covered), so its 'no match' says nothing about those assets.", "",
             *[f"- {md_cell(n, 1000)}" for n in notices], *([""] if notices else []),
             "| suspect | verdict | asset | recipient (issued copy) | score / threshold | p-value | margin | "
             "recipients checked | evidence |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        accused = json.loads(r["accused_json"]) if r.get("accused_json") else []
        who = "; ".join(f"{a['recipient']} ({', '.join(Path(p).name for _, p in a.get('copies', []) if p) or 'exact copy'})"
                        for a in accused) or "-"
        score = f"{r['score']:.1f} / {r['threshold']:.1f}" if r.get("score") is not None and r.get("threshold") else "-"
        p = f"{r['p_value']:.2g}" if r.get("p_value") is not None else "-"
        margin = f"{r['margin']:.1f}" if r.get("margin") is not None else "-"
        picture = f"[picture](evidence/{md_cell(Path(r['evidence_path']).name)})" if r.get("evidence_path") else "-"
        note = f" ({r['error']})" if r.get("error") else ""
        if r.get("note"):
            note += f" ({r['note']})"
        if r.get("registration_status") == "registration failed" and r["verdict"] != "match":
            note += " (registration failed on every candidate: the suspect may hold the asset in a form not reached)"
        cells = [Path(r["suspect_path"]).name, r["verdict"] + note, r.get("candidate_asset") or "-", who]
        lines.append("| " + " | ".join(md_cell(c, 600) for c in cells)
                     + f" | {score} | {p} | {margin} | {r.get('n_checked') or '-'} | {picture} |")
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())
    return Path(path)
