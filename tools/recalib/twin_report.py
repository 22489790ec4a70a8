"""Markdown tables of the twin recalibration bench (tools.recalib.twin_bench results)."""
from __future__ import annotations

import logging

log = logging.getLogger(__name__)


def markdown(res: dict, held: str = "probe") -> str:
    lines = [("| unit | variation (unknown to model + calibration) | held-out pokes | mean \\|F\\| (N) | pokes | "
             "held-out \\|F\\| MAE before → after (N) | reduction | forced | re-crop only (N) | LOO MAE before → after (N) | stored |"),
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["units"]:
        h = r["held_out"].get(held)
        if h is None:
            continue
        name = f"{r['unit']}{' (nominal)' if r.get('nominal') else ''}"
        for n, e in r["by_pokes"].items():
            a = h["after"].get(n)
            if a is None:
                lines.append(f"| {name} | {r['label']} | {h['pokes']} | {h['mean_ref_n']:.2f} | {n} | "
                             f"{e.get('error', '?')} | | | | | |")
                continue
            lines.append(f"| {name} | {r['label']} | {h['pokes']} | {h['mean_ref_n']:.2f} | {n} ({e['accepted']}) | "
                         f"{h['before_mae_n']:.3f} → {a['after_mae_n']:.3f} | {a['reduction']:.0%} | "
                         f"{a['reduction_forced']:.0%} | {h.get('crop_only_mae_n', float('nan')):.3f} | {e['loo_before_mae_n']:.3f} → {e['loo_after_mae_n']:.3f} | "
                         f"{'yes' if e['stored'] else 'no'} |")
    return "\n".join(lines)


def summary(res: dict, held: str = "probe") -> str:
    """One line per unit: before, re-crop only, after with 5/6/7 pokes (decided), inputs chosen."""
    counts = [str(n) for n in res.get("poke_counts", (5, 6, 7))]
    lines = ["| unit | variation | before (N) (pokes) | re-crop only (N) (pokes) | "
             + " | ".join(f"after, {n} pokes (N) (pokes)" for n in counts) + " | reduction " + " / ".join(counts)
             + " | inputs chosen " + " / ".join(counts) + " | oracle constant gain (N) |", "|---" * (7 + len(counts)) + "|"]
    for r in res["units"]:
        h = r["held_out"].get(held)
        if h is None:
            continue
        after = [h["after"].get(n) for n in counts]
        cells = [f"{a['after_mae_n']:.3f} ({a['pokes']}){'' if r['by_pokes'][n].get('stored') else ' refused'}"
                 if a else "—" for a, n in zip(after, counts)]
        red = " / ".join(f"{a['reduction']:.0%}" if a else "0%" for a in after)
        inp = " / ".join("+".join(r["by_pokes"][n].get("inputs", ["—"])) for n in counts)
        name = f"{r['unit']}{' (nominal)' if r.get('nominal') else ''}"
        lines.append(f"| {name} | {r['label']} | {h['before_mae_n']:.3f} ({h['pokes']}) | "
                     f"{h.get('crop_only_mae_n', float('nan')):.3f} ({h.get('crop_only_pokes', '?')}) | "
                     + " | ".join(cells) + f" | {red} | {inp} | {h.get('oracle_mae_n', float('nan')):.3f} |")
    return "\n".join(lines)
