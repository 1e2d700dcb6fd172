"""Rows of a result record as the scripts that write records emit them (docs/results/*.json; the schema is in
train/xtask/src/results_page/mod.rs): each row's id first, and what a person added by hand carried over."""

# Fields a person adds to a row by hand, kept when a script writes the record again.
HAND_KEPT = ('brief', 'detail', 'archived')


def carried(row, old):
    """`row` with what the record's row `old` (None: none) keeps by hand: its brief while the cells read the same,
    its detail and archived."""
    if old is None:
        return row
    row = dict(row)
    if 'brief' in old and old.get('cells') == row['cells']:
        row['brief'] = old['brief']
    for key in ('detail', 'archived'):
        if key in old:
            row[key] = old[key]
    return row


def numbered(rows, number):
    """The rows with `"id": "NN.K"` first (K: the place in `rows`, from 1), then cells and the hand-kept fields."""
    out = []
    for k, row in enumerate(rows, 1):
        head = {'id': f'{number}.{k}'}
        for key in ('cells',) + HAND_KEPT:
            if key in row:
                head[key] = row[key]
        head.update((key, value) for key, value in row.items() if key not in head)
        out.append(head)
    return out
