"""Updates the rows of docs/results/36-speed-vs-error.json from the test evaluations and step-time fits it names (run
from the repository root after docs/scripts/step_times.sh and the `eval` commands in the record).

The record is the store: a row whose evaluation is not on this machine (`out/` is rebuilt on a new checkout) keeps
the figures the record already holds, and the script says so. A row whose evaluation is here is written afresh from
its `metrics.json`, after its run's `config.json` is checked against the row's width, rate and length. The step
times are those of the AMD EPYC sitting (`out/speed/w*.log` when present, else the record's rows), so every row's
CPU-hours share one machine. The title, intro, plot and notes are prose kept in the record by hand.

Each row gets its id (`36.K`, K its place) and a brief, the page's short form of its cells; a row the record already
holds (same command) keeps its hand-written brief while its cells read the same, and its `detail` and `archived`."""
import json
import os
import re
import sys

from record_rows import carried, numbered

RECORD = 'docs/results/36-speed-vs-error.json'
AMD = 'session of 2026-11-26 (seventh), AMD EPYC 2-core build machine, release build'
INTEL = ('session of 2026-11-28 (seventeenth), Intel Xeon (AVX-512) 2-core build machine, release build; CPU-hours '
         'at the AMD step time of its width, like the rows above')
EVAL = 'g2r-train eval --run {run} --data out/tycho-dataset/dataset --split test'
SHIPPED = 'train/shipped/tycho-full-h1'

# (point: the plot's label, empty where a row shares its x with the one above; width, lr, steps, run, eval dir (None:
# the record's figures stand), what the cells add to the run's name, what the brief adds, extra eval flags, measured)
ROWS = [
    ('w4 4k lr1e-4', 4, '1e-4', 4000, 'out/runs/h1-w4', 'out/evals/h1-w4-test', '', '', ' --panels 0', AMD),
    ('', 8, '1e-4', 4000, 'out/runs/h1', 'out/evals/h1-test', '', '', ' --world out/tycho-world',
     'test score: session of 2026-11-26 (first); step time: the seventh'),
    ('w8 4k (lr 1e-4 and 1e-3)', 8, '1e-3', 4000, 'out/runs/h1-lr1e-3', 'out/evals/h1-lr1e-3-test', '', '',
     ' --panels 0', AMD),
    ('w8 8k', 8, '1e-3', 8000, 'out/runs/h1-lr1e-3-2ep', 'out/evals/h1-lr1e-3-2ep-test', '', '', ' --panels 0',
     AMD),
    # The 16,000-step checkpoint was replaced by the 32,000-step one in the same folder: its row is the record's.
    ('w8 16k', 8, '1e-3', 16000, SHIPPED, None,
     ' — the shipped model until the 32,000-step one', ' (shipped before)', ' --world out/tycho-world', AMD),
    ('w8 32k (shipped; third run)', 8, '1e-3', 32000, SHIPPED, 'out/evals/shipped32k-test', ' — **the shipped model**',
     ': **the shipped network**', ' --world out/tycho-world --out out/evals/shipped32k-test',
     'session of 2026-11-27 (eleventh), AMD EPYC 2-core build machine, release build; CPU-hours at the same step '
     'time as the rows above (0.224 s)'),
    ('', 8, '1e-3', 32000, 'out/runs/h1-intel-8ep', 'out/evals/intel32k-test',
     ' — the shipped command run a third time', ': its third run',
     ' --world out/tycho-world --out out/evals/intel32k-test', INTEL.replace('seventeenth', 'sixteenth')),
    ('w8 48k', 8, '1e-3', 48000, 'out/runs/h1-12ep', 'out/evals/h1-12ep-test',
     ' — twelve epochs, turned down on validation (record 35), scored here for this table only',
     ': turned down (35.17)', ' --checkpoint last --panels 0 --out out/evals/h1-12ep-test',
     'sessions of 2026-11-28 (eighteenth and nineteenth), Intel Xeon (AVX-512) 2-core build machine, release build; '
     'CPU-hours at the AMD step time of its width, like the rows above'),
    ('w16 4k', 16, '1e-3', 4000, 'out/runs/h1-w16-1ep', 'out/evals/w16-4k-test', '', '',
     ' --panels 0 --out out/evals/w16-4k-test', INTEL),
]
# Fields a record's row keeps by hand: placed after its cells, in this order.


def amd_step_times(record):
    """s/step by width: from the AMD step-time logs when present, else from the record's rows."""
    logs = {w: f'out/speed/w{w}.log' for w in (4, 8, 16)}
    if all(os.path.exists(p) for p in logs.values()):
        return {w: 8.0 / float(re.findall(r'samples_per_s="([0-9.]+)"', open(p).read())[-1])
                for w, p in logs.items()}
    times = {}
    for row in record['rows']:
        f = row['figures']
        times.setdefault(int(f['width']), f['s_per_step'])
    return times


def checked_config(run, width, lr, steps):
    config = json.load(open(os.path.join(run, 'config.json')))
    last = [json.loads(line) for line in open(os.path.join(run, 'metrics.jsonl'))][-1]
    found = (config['base_width'], config['learning_rate'], last['steps'])
    if found != (width, float(lr), steps):
        sys.exit(f'{run}: width, rate and steps are {found}, the row says {(width, float(lr), steps)}')


def command_of(spec):
    point, width, lr, steps, run, ev, suffix, brief_suffix, flags, measured = spec
    return f'`{EVAL.format(run=run)}{flags}`'


def fresh_row(spec, m, s):
    """The row of `spec` (one of ROWS), without id, from its evaluation's metrics `m` and the step times `s`."""
    point, width, lr, steps, run, ev, suffix, brief_suffix, flags, measured = spec
    ck = m['learned_checkpoints'][0] if m['learned_checkpoints'] else ''
    rest = ['{crops_seen}', '{cpu_hours:.2}', '**{test_learned_over_paper_hapke_sse:.3}**', f'`{ck}`']
    return {
        'cells': [f'H1, width {width}, cosine lr {lr}, {steps:,} steps ({steps * 8:,} crops){suffix}'] + rest,
        'brief': [f'H1, width {width}, cosine lr {lr}, {steps:,} steps{brief_suffix}'] + rest,
        'command': command_of(spec),
        'measured': measured,
        'figures': {'width': width, 'steps': steps, 'crops_seen': steps * 8,
                    's_per_step': round(s[width], 3), 'cpu_hours': round(steps * s[width] * 2 / 3600, 3),
                    'test_learned_over_paper_hapke_sse': round(m['learned_over_hapke_paper_sse'], 4)},
        'point': point,
    }


def main():
    record = json.load(open(RECORD, encoding='utf-8'))
    kept = {r['command']: r for r in record['rows'] if 'cpu_hours' in r['figures']}
    s = amd_step_times(record)
    rows = []
    for spec in ROWS:
        point, width, lr, steps, run, ev, suffix, brief_suffix, flags, measured = spec
        metrics = os.path.join(ev, 'metrics.json') if ev else None
        command = command_of(spec)
        if not (metrics and os.path.exists(metrics)):
            if command not in kept:
                print(f'{run}: no {metrics} and no row in the record; left out', file=sys.stderr)
                continue
            why = f'no {metrics}' if metrics else 'its checkpoint is gone'
            print(f'{run}: {why}; the record\'s figures kept', file=sys.stderr)
            rows.append(dict(kept[command], point=point))
            continue
        checked_config(run, width, lr, steps)
        m = json.load(open(metrics, encoding='utf-8'))
        rows.append(carried(fresh_row(spec, m, s), kept.get(command)))
    # A width with a step time but no trained row yet keeps its step-time-only row.
    trained = {r['figures']['width'] for r in rows}
    rows += [r for r in record['rows'] if 'cpu_hours' not in r['figures'] and r['figures']['width'] not in trained]
    record['rows'] = numbered(rows, os.path.basename(RECORD).split('-')[0])
    open(RECORD, 'w', encoding='utf-8').write(json.dumps(record, indent=2, ensure_ascii=False) + '\n')


if __name__ == '__main__':
    main()
