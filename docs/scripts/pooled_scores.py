"""Learned / paper-Hapke SSE of one or more `g2r-train eval` outputs, each alone and pooled: overall, the Hapke → oracle
gap closed, and by terrain class, class × unit, incidence band and whether the crop's inputs lay within the run's
training range (evaluations of runs that keep one). Pooled as the records pool (60.18 on): each
method's pixel MSE times its crops, summed over the evaluations, so a bigger split weighs more; a ratio of pooled
pixel MSEs equals the ratio of pooled per-image SSEs, since every crop has the same pixel count.

    python docs/scripts/pooled_scores.py EVAL_DIR [EVAL_DIR ...]

Reads each EVAL_DIR/metrics.json only (no third-party modules).
"""
import json
import os
import sys

LEARNED, BASELINE, ORACLE = 'learned', 'hapke_paper', 'oracle'
BREAKDOWNS = ('terrain_class', 'terrain_class_and_unit', 'incidence_deg', 'training_range')


def overall(metrics):
    """{method: (crops, pixel MSE)} of the whole evaluation."""
    return {m['name']: (m['aggregate']['images'], m['aggregate']['pixel_mse_pooled']) for m in metrics['methods']}


def grouped(metrics, by):
    """{group: {method: (crops, pixel MSE)}} of one breakdown."""
    for breakdown in metrics['breakdowns']:
        if breakdown['by'] == by:
            return {g['group']: {name: (g['images'], mse) for name, mse in g['mean_pixel_mse'].items()}
                    for g in breakdown['groups']}
    return {}


def pool(parts):
    """Pooled {method: (crops, pixel MSE)} of several {method: (crops, pixel MSE)}."""
    sums = {}
    for part in parts:
        for name, (crops, mse) in part.items():
            total_crops, total = sums.get(name, (0, 0.0))
            sums[name] = (total_crops + crops, total + crops * mse)
    return {name: (crops, total / crops) for name, (crops, total) in sums.items() if crops}


def ratio(scores):
    return scores[LEARNED][1] / scores[BASELINE][1]


def gap_closed(scores):
    hapke, learned, oracle = (scores[m][1] for m in (BASELINE, LEARNED, ORACLE))
    return (hapke - learned) / (hapke - oracle)


def report(name, whole, breakdowns):
    print(f"{name}: {whole[LEARNED][0]} crops, learned / paper-Hapke {ratio(whole):.4f}, "
          f"gap closed {100 * gap_closed(whole):.1f} %")
    for by in BREAKDOWNS:
        cells = [f"{group} {ratio(scores):.3f} ({scores[LEARNED][0]})"
                 for group, scores in breakdowns[by].items() if scores[BASELINE][1] > 0]
        if cells:
            print(f"  by {by}: " + "; ".join(cells))


def main(dirs):
    if not dirs:
        sys.exit("usage: pooled_scores.py EVAL_DIR [EVAL_DIR ...]")
    wholes, breakdowns = [], []
    for d in dirs:
        path = os.path.join(d, 'metrics.json')
        try:
            with open(path) as f:
                metrics = json.load(f)
        except (OSError, ValueError) as e:
            sys.exit(f"{path}: {e}; pass the output folder of a finished `g2r-train eval`")
        wholes.append(overall(metrics))
        breakdowns.append({by: grouped(metrics, by) for by in BREAKDOWNS})
        report(d, wholes[-1], breakdowns[-1])
    if len(dirs) > 1:
        pooled = {by: {} for by in BREAKDOWNS}
        for by in BREAKDOWNS:
            groups = dict.fromkeys(g for b in breakdowns for g in b[by])  # in the order they first appear
            for group in groups:
                pooled[by][group] = pool([b[by][group] for b in breakdowns if group in b[by]])
        report("pooled", pool(wholes), pooled)


if __name__ == '__main__':
    main(sys.argv[1:])
