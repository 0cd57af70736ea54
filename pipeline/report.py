"""The evaluation report: PNG plots and a Markdown summary, from the trial rows."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

__all__ = ["write_report"]

# the paper's own statements (section 3.1), per attack chain of configs/evaluate-paper.yaml
PAPER_SAYS = {
    "none": "0 errors",
    "similarity": "0 errors",
    "noise:0.5%": "0 errors",
    "noise:0.8%": "lost (partly)",
    "removal:0.139": "0 errors",
    "crop:0.5": "0 errors (one cluster whole)",
    "resample:10000": "0 errors",
    "resample:5000": "lost",
    "similarity+removal:0.139": "lost (registration)",
    "resample:10000+random_similarity": "lost (registration)",
}


# the experiment whose rows make the Figure-8 curves; every other one is an attack table
NOISE_CURVE = "noise_curve"
METHOD_ORDER = ("paper", "robust-xyz", "robust")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _group(rows, keys):
    groups = defaultdict(list)
    for r in rows:
        groups[tuple(r[k] for k in keys)].append(r)
    return groups


def plot_noise_curves(rows, path):
    """BER against noise amplitude, one line per (beta, c), one panel per method (Figure 8)."""
    plt = _plt()
    noise = [r for r in rows if r["experiment"] == NOISE_CURVE]
    methods = [m for m in METHOD_ORDER if m in {r["method"] for r in noise}]
    if not noise:
        return None
    fig, axes = plt.subplots(1, len(methods), figsize=(6 * len(methods), 4.5), squeeze=False, sharey=True)
    for ax, method in zip(axes[0], methods):
        lines = _group([r for r in noise if r["method"] == method], ("beta", "chip_rate"))
        for (beta, c), rs in sorted(lines.items()):
            pts = _group(rs, ("strength",))
            x = sorted(k[0] for k in pts)
            y = [np.mean([r["ber"] for r in pts[(v,)]]) for v in x]
            ax.plot(100 * np.array(x), y, marker="o", label=f"beta = {beta}, c = {c}")
        ax.set_title(f"method: {method}")
        ax.set_xlabel("noise amplitude (% of largest bbox side)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0][0].set_ylabel("bit error rate (mean over runs)")
    fig.suptitle("BER against uniform noise (cf. the paper's Figure 8)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_attacks(rows, path):
    """Mean BER per attack chain, one bar per method, one panel per model."""
    plt = _plt()
    table = _group([r for r in rows if r["experiment"] not in (NOISE_CURVE, RATE_DISTORTION)],
                   ("model", "attack", "method"))
    models = sorted({k[0] for k in table})
    methods = [m for m in METHOD_ORDER if m in {k[2] for k in table}]
    if not models:
        return None
    attacks = {m: sorted({a for mm, a, _ in table if mm == m}) for m in models}
    fig, axes = plt.subplots(
        len(models), 1, figsize=(9, 1.2 + 0.42 * sum(len(a) for a in attacks.values()) + 0.5 * len(models)),
        squeeze=False, sharex=True, gridspec_kw={"height_ratios": [len(attacks[m]) for m in models]},
    )
    height = 0.8 / len(methods)
    for ax, model in zip(axes[:, 0], models):
        names = attacks[model]
        for i, method in enumerate(methods):
            y = np.arange(len(names)) + (i - (len(methods) - 1) / 2) * height
            ber = [np.mean([r["ber"] for r in table.get((model, a, method), [])] or [np.nan])
                   for a in names]
            ax.barh(y, ber, height, color=f"C{i}", label=f"method: {method}")
            for yy, b in zip(y, ber):   # print the value, so that a zero is visible too
                if np.isfinite(b):
                    ax.text(b + 0.005, yy, f"{b:.3g}", va="center", fontsize=7)
        ax.set_yticks(np.arange(len(names)))
        ax.set_yticklabels(names, fontsize=8)
        ax.invert_yaxis()
        ax.set_title(model, fontsize=9, loc="left")
        ax.grid(axis="x", alpha=0.3)
    axes[-1, 0].set_xlim(0, 0.75)
    axes[-1, 0].set_xlabel("bit error rate (fraction of payload bits wrong, mean over runs; 0 = intact)")
    fig.suptitle("Bit error rate per attack: the paper's method against the robust one")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(methods), fontsize=8,
               bbox_to_anchor=(0.5, 1 - 0.45 / fig.get_figheight()))
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.7 / fig.get_figheight()))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_false_positives(fp_rows, path):
    """Empirical rate of wrong-key p-values below t, against t."""
    plt = _plt()
    wrong = [r for r in fp_rows if r["key"] >= 0]
    if not wrong:
        return None
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    t = np.logspace(-4, 0, 50)
    for label, rs in sorted(_group(wrong, ("suspect",)).items()):
        p = np.array([r["p_value"] for r in rs])
        ax.loglog(t, [(p < v).mean() for v in t], label=f"{label[0]} ({len(p)} keys x models)")
    ax.loglog(t, t, "k--", label="stated rate (p-value threshold)")
    ax.set_xlabel("p-value threshold")
    ax.set_ylabel("fraction of wrong keys reported present")
    ax.set_title("False positives with wrong keys")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


RATE_DISTORTION = "rate-distortion"


def variant(row):
    """Label of an embedding and detector pair."""
    if row["method"] == "paper":
        return "paper embedding, paper detector"
    if row["method"] == "robust-xyz":
        return "paper embedding, robust detector"
    return f"{row['displacement']}, {row.get('code', 'repetition')}, robust detector"


PAPER_BETA = 0.002
_CURVE = ("method", "displacement", "code", "chip_layout", "chip_rate")


def rate_distortion_curves(rows):
    """{(model, attack): {variant: (distance, ber, mer, trials, beta) arrays by beta}}, distance = MRMS / diag."""
    rd = [{"code": "repetition", "chip_layout": None, **r} for r in rows if r["experiment"] == RATE_DISTORTION]
    distance = {k: np.mean([r["mrms_rel_diag"] for r in rs])
                for k, rs in _group(rd, ("model", *_CURVE, "beta")).items()}
    curves = defaultdict(dict)
    for (model, attack), rs in _group(rd, ("model", "attack")).items():
        for label, vs in _group(rs, _CURVE).items():
            cells = sorted(_group(vs, ("beta",)).items())
            x = np.array([distance[(model, *label, b)] for (b,), _ in cells])
            ber = np.array([np.mean([r["ber"] for r in c]) for _, c in cells])
            mer = np.array([np.mean([r["message_error"] for r in c]) for _, c in cells])
            n = np.array([len(c) for _, c in cells])
            name = variant(vs[0])
            if label[4] != 10 or name in curves[(model, attack)]:
                name += f", c = {label[4]}, {label[3]}"
            curves[(model, attack)][name] = (x, ber, mer, n, np.array([b for (b,), _ in cells]))
    return curves


def _paper_distance(curve):
    """Distance of the paper's embedding at the paper's beta (the middle point if it was not run)."""
    x, beta = curve[0], curve[4]
    at = np.flatnonzero(np.isclose(beta, PAPER_BETA))
    return float(x[at[0]]) if len(at) else float(np.median(x))


def _at(curve, x0, slack=1e-9):
    """Value of a curve (x ascending) at x0, linear in log x; nan outside its range widened by ``slack`` (log)."""
    x, y = curve
    order = np.argsort(x)
    x, y = np.log(x[order]), y[order]
    if not (x[0] - slack <= np.log(x0) <= x[-1] + slack):
        return float("nan")
    return float(np.interp(np.log(x0), x, y))


READ_SLACK = np.log(1.02)   # a fingerprint curve within 2 % of a distance is read there (at its end point)


def _distance_axis(plt, ax, ticks=None):
    """A log x axis of MRMS (% of the diagonal), gridded; labelled at ``ticks`` where given."""
    ax.set_xscale("log")
    if ticks is not None:
        ax.set_xticks(ticks)
        ax.tick_params(axis="x", labelrotation=45, labelsize=8)
    ax.xaxis.set_major_formatter(plt.matplotlib.ticker.FormatStrFormatter("%.3g" if ticks is None else "%.4f"))
    ax.xaxis.set_minor_formatter(plt.matplotlib.ticker.NullFormatter())
    ax.grid(alpha=0.3, which="both")


def _save(plt, fig, path):
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_rate_distortion(rows, folder):
    """BER and message error rate against MRMS, one figure per model, one column per attack."""
    curves = rate_distortion_curves(rows)
    if not curves:
        return []
    plt = _plt()
    paths = []
    for model in sorted({m for m, _ in curves}):
        attacks = sorted(a for m, a in curves if m == model)
        colours = {v: f"C{i}" for i, v in enumerate(sorted({v for a in attacks for v in curves[(model, a)]}))}
        fig, axes = plt.subplots(2, len(attacks), figsize=(4.2 * len(attacks), 7), squeeze=False, sharex=True)
        for col, attack in enumerate(attacks):
            for label, (x, ber, mer, n, _) in sorted(curves[(model, attack)].items()):
                for row, y in ((0, ber), (1, mer)):
                    axes[row, col].plot(100 * x, y, marker="o", color=colours[label], label=label)
            paper = curves[(model, attack)].get("paper embedding, paper detector")
            for row in (0, 1):
                ax = axes[row, col]
                if paper is not None:
                    ax.axvline(100 * _paper_distance(paper), color="grey", ls=":", lw=1)
                _distance_axis(plt, ax)
                ax.set_ylim(-0.03, 1.03 if row else 0.7)
            axes[0, col].set_title(attack, fontsize=10)
            axes[1, col].set_xlabel("MRMS distance to the surface (% of diagonal)")
        axes[0, 0].set_ylabel("bit error rate")
        axes[1, 0].set_ylabel("message error rate (any bit wrong)")
        handles = [plt.matplotlib.lines.Line2D([], [], color=c, marker="o") for c in colours.values()]
        fig.legend(handles, list(colours), loc="upper center", ncol=2, fontsize=8, bbox_to_anchor=(0.5, 0.965))
        fig.suptitle(f"{model}: rate-distortion at equal detector (dotted: the paper's beta 0.002)", y=0.995,
                     fontsize=10)
        fig.tight_layout(rect=(0, 0, 1, 0.89))
        paths.append(_save(plt, fig, Path(folder) / f"rate_distortion_{model}.png"))
    return paths


def rate_distortion_lines(rows):
    """Markdown: each variant at the paper's distance to the surface, and the equal-distortion check."""
    curves = rate_distortion_curves(rows)
    if not curves:
        return []
    table, worse, compared, apart = [], [], 0, []
    for (model, attack), by in sorted(curves.items()):
        paper = by.get("paper embedding, paper detector")
        if paper is None:
            continue
        x0 = _paper_distance(paper)
        for label, (x, ber, mer, n, _) in sorted(by.items()):
            table.append([model, attack, label, f"{100 * x0:.4f}", f"{_at((x, ber), x0):.3f}",
                          f"{_at((x, mer), x0):.2f}", int(n.min())])
            if "robust detector" not in label:
                continue
            for xp, mp in zip(paper[0], paper[2]):
                m = _at((x, mer), xp)
                if not np.isfinite(m):
                    apart.append(f"{model}, {attack}, {label} at {100 * xp:.4f} % (paper: {mp:.2f})")
                    continue
                compared += 1
                if m > mp + 1e-9:
                    worse.append(f"{model}, {attack}, {label}: {m:.2f} against {mp:.2f} at {100 * xp:.4f} %")
    return ["## Rate-distortion", "",
            "Each curve is one embedding with one detector, beta swept on a sqrt(3) ladder; distance is the "
            "MRMS between the surfaces (local tangent planes, both ways). Values at the paper's distance (its "
            "embedding at beta 0.002) are read off each curve, linear in log distance ('nan': outside the "
            "curve's range). Message error rate: share of trials with any payload bit wrong.", "",
            _md_table(["model", "attack", "embedding, detector", "distance (% diag)", "BER", "message error rate",
                       "trials per point"], table), "",
            f"Robust-detector curves against the paper's at each of the paper's distortions: {compared} "
            "comparisons inside both curves' ranges; higher message error rate than the paper's: "
            + ("; ".join(worse) if worse else "nowhere") + ".",
            "", "Outside a curve's range (not compared): " + ("; ".join(apart) if apart else "none") + ".", ""]


def _md_table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def fingerprint_lines(rows):
    """Markdown section of the fingerprint trials: accusations per model, case and attack."""
    if not rows:
        return []
    table = []
    cells = _group([{"beta": None, **r} for r in rows], ("model", "case", "attack", "beta"))
    for (model, case, attack, beta), rs in sorted(cells.items(), key=lambda kv: (*kv[0][:3], kv[0][3] or 0.0)):
        k = rs[0]["colluders"]
        hit = sum(r["accused_colluders"] > 0 for r in rs)
        every = sum(r["accused_colluders"] == k for r in rs) if k else 0
        scores = [r["min_colluder_score"] for r in rs if k]
        table.append([model, case, attack, "-" if beta is None else f"{beta:.6f}", len(rs), rs[0]["n_recipients"],
                      f"{max(r['threshold'] for r in rs):.2f}",
                      f"{hit}/{len(rs)}" if k else "-", f"{every}/{len(rs)}" if k else "-",
                      f"{min(scores):.1f}" if scores else "-", sum(r["accused_innocents"] for r in rs),
                      f"{max(r['max_innocent_score'] for r in rs):.2f}"])
    checks = sum(r["innocent_checks"] for r in rows)
    tails = [[f">= {t}", sum(r[f"innocents_over_{t}"] for r in rows), f"{sum(r[f'innocents_over_{t}'] for r in rows) / checks:.2e}",
              f"{np.exp(-t * t / 2):.2e}"] for t in (2, 3, 4)]
    eps = rows[0]["epsilon"]
    return ["## Recipient fingerprints and collusion", "",
            f"Each trial issues fingerprinted copies to {rows[0]['n_recipients']} recipients; colluders average their "
            "copies or take each point from one of them at random; the suspect is attacked and shuffled. A "
            f"recipient is accused when the score clears sqrt(2 ln(n / eps)), eps = {eps:g} per suspect.", "",
            _md_table(["model", "case", "attack", "beta", "trials", "recipients", "threshold (highest)",
                       ">= 1 colluder accused",
                       "all colluders accused", "lowest colluder score", "innocents accused",
                       "highest innocent score"], table), "",
            f"Innocent checks: {checks:,}. Share of innocent scores over t, against the bound exp(-t^2/2) "
            "that the threshold is built on:", "",
            _md_table(["score", "innocents", "share", "bound"], tails), ""]


PAPER_DISTANCE = "paper-distance"   # message rows of the paper's embedding (beta 0.002, xyz): its distance
CHO_DISTANCE = 0.00012               # Cho et al. 2007: MRMS 0.008-0.012 % of the diagonal (the upper end)


def paper_distances(rows):
    """{model: MRMS / diag of the paper's embedding} from the ``paper-distance`` experiment's rows."""
    return {model: float(np.mean([r["mrms_rel_diag"] for r in rs]))
            for (model,), rs in _group([r for r in rows if r["experiment"] == PAPER_DISTANCE], ("model",)).items()}


def fingerprint_curves(rows):
    """{model: {"case, attack": (distance, named, margin, trials, beta) arrays by beta}} of cells at 2+ betas.

    ``named``: share of trials with a colluder accused; ``margin``: the
    median over trials of the lowest colluder score less the threshold.
    """
    curves = defaultdict(dict)
    marked = [r for r in rows if r["colluders"] and r.get("beta") is not None]
    for (model, case, attack), rs in _group(marked, ("model", "case", "attack")).items():
        cells = sorted(_group(rs, ("beta",)).items())
        if len(cells) < 2:
            continue
        curves[model][f"{case}, {attack}"] = (
            np.array([np.mean([r["mrms_rel_diag"] for r in c]) for _, c in cells]),
            np.array([np.mean([r["accused_colluders"] > 0 for r in c]) for _, c in cells]),
            np.array([np.median([r["min_colluder_score"] - r["threshold"] for r in c]) for _, c in cells]),
            np.array([len(c) for _, c in cells]), np.array([b for (b,), _ in cells]))
    return curves


def plot_fingerprint_rate_distortion(rows, message_rows, folder):
    """Leaker named, and the margin over the threshold, against MRMS: one figure per model."""
    curves, paper = fingerprint_curves(rows), paper_distances(message_rows)
    if not curves:
        return []
    plt = _plt()
    paths = []
    for model, by in sorted(curves.items()):
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), squeeze=False)
        for i, (label, (x, named, margin, n, _)) in enumerate(sorted(by.items())):
            axes[0, 0].plot(100 * x, named, marker="o", color=f"C{i}", label=label)
            axes[0, 1].plot(100 * x, margin, marker="o", color=f"C{i}")
        ticks = sorted({round(100 * v, 4) for x, *_ in by.values() for v in x})
        if min(abs(np.log(t / (100 * CHO_DISTANCE))) for t in ticks) > 0.05:     # no two labels on one spot
            ticks = sorted([*ticks, 100 * CHO_DISTANCE])
        for ax in axes[0]:
            ax.axvline(100 * CHO_DISTANCE, color="grey", ls="--", lw=1)
            if model in paper:
                ax.axvline(100 * paper[model], color="grey", ls=":", lw=1)
            _distance_axis(plt, ax, ticks)
            ax.set_xlabel("MRMS distance to the surface (% of diagonal)")
        axes[0, 0].set_ylim(-0.03, 1.03)
        axes[0, 0].set_ylabel("share of trials with the leaker named")
        axes[0, 1].axhline(0.0, color="black", lw=0.8)
        axes[0, 1].set_ylabel("lowest leaker score - threshold (median)")
        fig.suptitle(f"{model}: fingerprints against distance (dotted: the paper's embedding, dashed: Cho 0.012 %)",
                     y=0.99, fontsize=10)
        fig.legend(loc="upper center", ncol=3, fontsize=8, bbox_to_anchor=(0.5, 0.94))
        fig.tight_layout(rect=(0, 0, 1, 0.8))
        paths.append(_save(plt, fig, Path(folder) / f"fingerprint_rate_distortion_{model}.png"))
    return paths


def fingerprint_rate_distortion_lines(rows, message_rows):
    """Markdown: each fingerprint curve read at the paper's distance and at Cho's 0.012 %."""
    curves, paper = fingerprint_curves(rows), paper_distances(message_rows)
    table = []
    for model, by in sorted(curves.items()):
        for label, (x, named, margin, n, _) in sorted(by.items()):
            at = [paper.get(model, float("nan")), CHO_DISTANCE]
            table.append([model, label, int(n.min()), *[f"{_at((x, named), x0, READ_SLACK):.2f}, "
                                                         f"{_at((x, margin), x0, READ_SLACK):+.2f}"
                                                         if np.isfinite(x0) else "-" for x0 in at],
                          f"{100 * x.min():.4f}-{100 * x.max():.4f}"])
    if not table:
        return []
    return ["## Fingerprints against distance", "",
            "Each curve is one fingerprint configuration with one detector, beta swept; distance is the MRMS "
            "between the surfaces of one recipient's copy and the original. Read off each curve (linear in log "
            "distance; within 2 % of its ends, the end point; 'nan' further out): the share of trials naming a "
            "leaker, and the median margin of the lowest leaker score over the threshold, at the paper's "
            "distance (its embedding, beta 0.002, "
            "xyz, on the same model) and at Cho et al.'s 0.012 % of the diagonal.", "",
            _md_table(["model", "case, attack", "trials per point", "at the paper's distance", "at 0.012 %",
                       "distances run (% diag)"], table), ""]


def write_report(folder, rows, fp_rows, p_threshold, seconds, fingerprint_rows=()):
    """Write plots and summary.md into ``folder``."""
    folder = Path(folder)
    plots = [plot_attacks(rows, folder / "attacks.png"), plot_noise_curves(rows, folder / "noise_curves.png"),
             plot_false_positives(fp_rows, folder / "false_positives.png"),
             *plot_rate_distortion(rows, folder),
             *plot_fingerprint_rate_distortion(list(fingerprint_rows), rows, folder)]
    lines = ["# pointmark evaluation", "",
             f"{len(rows)} trials in {seconds:.0f} s. BER = bit errors / payload bits; every attacked "
             "copy was shuffled before detection.", ""]
    attack_rows = []
    present = {r["method"] for r in rows}
    methods = [m for m in METHOD_ORDER if m in present]
    for (exp, model, attack), rs in sorted(_group([r for r in rows
                                                   if r["experiment"] not in (NOISE_CURVE, RATE_DISTORTION)],
                                                  ("experiment", "model", "attack")).items()):
        by = _group(rs, ("method",))
        cells = []
        for method in methods:
            m = by.get((method,), [])
            cells.append("-" if not m else f"{np.mean([r['ber'] for r in m]):.3f} "
                         f"({sum(r['bit_errors'] == 0 for r in m)}/{len(m)} exact)")
        attack_rows.append([exp, model, attack, *cells, PAPER_SAYS.get(attack, "")])
    if attack_rows:
        lines += ["## Attacks", "", _md_table(["experiment", "model", "attack",
                                              *[f"BER, {m}" for m in methods], "the paper reports"],
                                             attack_rows), ""]
    lines += rate_distortion_lines(rows)
    noise = [r for r in rows if r["experiment"] == NOISE_CURVE]
    if noise:
        curve = []
        for (method, beta, c, s), rs in sorted(_group(noise, ("method", "beta", "chip_rate", "strength")).items()):
            curve.append([method, beta, c, f"{100 * s:.2f} %", f"{np.mean([r['ber'] for r in rs]):.3f}", len(rs)])
        lines += ["## BER against noise (Figure 8)", "",
                  _md_table(["method", "beta", "c", "noise", "mean BER", "runs"], curve), ""]
    dist = _group([{"code": "repetition", **r} for r in rows],
                  ("model", "n_clusters", "beta", "chip_rate", "displacement", "code"))
    measures = ("rmse_rel_diag", "hausdorff_rel_diag", "surface_rmse_rel_diag", "mrms_rel_diag",
                "surface_hausdorff_rel_diag")

    def mean(rs, k, scale):
        values = [r[k] for r in rs if r.get(k) is not None]
        return f"{scale * np.mean(values):.4f}" if values else "-"

    lines += ["## Distortion", "",
              "RMSE and Hausdorff as in ROBUSTNESS.md; surface RMS: distance of the marked points to the "
              "tangent planes of the original (one way); MRMS and surface Hausdorff: between the two "
              "surfaces (tangent planes of each, both ways, the larger); normal deviation in degrees; "
              "MSDM-style roughness distance (0: same roughness).", "", _md_table(
                  ["model", "clusters", "beta", "c", "displacement", "code", "RMSE (% diag)", "Hausdorff (% diag)",
                   "surface RMS (% diag)", "MRMS (% diag)", "surface Hausdorff (% diag)", "normal dev. (deg)",
                   "MSDM"],
                  [[*key, *[mean(rs, k, 100) for k in measures], mean(rs, "normal_deviation_deg", 1),
                    mean(rs, "msdm", 1)] for key, rs in sorted(dist.items())]), ""]
    if fp_rows:
        fp = []
        for (label,), rs in sorted(_group(fp_rows, ("suspect",)).items()):
            p = np.array([r["p_value"] for r in rs])
            fp.append([label, len(p)] + [f"{(p < t).mean():.4f}" for t in (0.1, 0.01, 0.001, p_threshold)])
        lines += ["## False positives", "",
                  f"Detection says 'watermarked' when p < {p_threshold:g}; under the null the p-value is "
                  "uniform, so a threshold t should flag a fraction t of wrong keys.", "",
                  _md_table(["suspect", "keys", "p<0.1", "p<0.01", "p<0.001", f"p<{p_threshold:g}"], fp), ""]
    lines += fingerprint_lines(list(fingerprint_rows))
    lines += fingerprint_rate_distortion_lines(list(fingerprint_rows), rows)
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots if p is not None]
    (folder / "summary.md").write_text("\n".join(lines) + "\n")
    return folder / "summary.md"
