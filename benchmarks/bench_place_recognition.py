"""Does a place-recognition query stay cheap as the keyframe database grows?

Trains (or loads from the cache) slamkit's default ORB vocabulary (:func:`slamkit.place_recognition.
default_vocabulary`: every 4th frame of the default sequence, branching 10, depth 4), extracts ORB from the
360 frames of the default sequence, and fills a :class:`PlaceDatabase` with up to ``--sizes`` keyframes.
Keyframes beyond the 360 real ones are synthesised so that their bags of words keep real word statistics:
each is the union of random halves of the descriptors of two random frames (distinct bags, real words).
Reported per size: median and 95th percentile wall time of ``query(descriptors, k=10)`` over ``--queries``
real frames (the bag of words included), the time of the inverted-file scoring alone (``query_bow``), the
time of ``add``, and the mean number of posting entries a query visits, with the default query budget
(``max_postings``) and without one (``full``); and recall@1 of both: the query is the same view rendered live
with other image noise and no JPEG (``synthetic:default?noise=1``), right when the top keyframe is within
two frames of it (over the queries whose frame is in the database).

Usage::

    nice -n 5 .venv/bin/python benchmarks/bench_place_recognition.py
    .venv/bin/python benchmarks/bench_place_recognition.py --sizes 100 1000 --queries 20
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from slamkit import open_source
from slamkit.features import create_extractor
from slamkit.place_recognition import PlaceDatabase, default_vocabulary


def _timed(fn, *args, **kw) -> tuple[float, object]:
    t = time.perf_counter()
    out = fn(*args, **kw)
    return time.perf_counter() - t, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 1000, 5000])
    ap.add_argument("--queries", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    t_voc, vocabulary = _timed(default_vocabulary, "orb")
    print(f"vocabulary: {vocabulary} ({t_voc:.1f} s to train or load)")
    orb = create_extractor("orb")
    seq = open_source("default")
    descs = [orb.extract(f.gray).descriptors for f in seq]
    t_bow = [_timed(vocabulary.bow, d)[0] for d in descs[:50]]
    print(f"bag of words of one frame ({np.mean([len(d) for d in descs]):.0f} ORB): "
          f"{1e3 * np.median(t_bow):.2f} ms median")
    rng = np.random.default_rng(args.seed)
    live = open_source("synthetic:default?noise=1")
    picks = rng.choice(len(descs), size=args.queries, replace=False)
    queries = [orb.extract(live[int(p)].gray).descriptors for p in picks]
    db = PlaceDatabase(vocabulary)
    budget = db.max_postings
    add_times: list[float] = []
    print(f"{'keyframes':>9} {'budget':>7} {'query ms (median/p95)':>22} {'scoring ms':>11} {'add ms':>7} "
          f"{'postings':>9} {'recall@1':>8}")
    for size in sorted(args.sizes):
        while len(db) < size:
            i = len(db)
            if i < len(descs):
                d = descs[i]
            else:
                a, b = rng.integers(len(descs), size=2)
                d = np.vstack([descs[a][rng.random(len(descs[a])) < 0.5], descs[b][rng.random(len(descs[b])) < 0.5]])
            add_times.append(_timed(db.add, i, d)[0])
        for db.max_postings in (budget, None):
            q_times = [_timed(db.query, q, k=10)[0] for q in queries]
            bows = [vocabulary.bow(q) for q in queries]
            s_times = [_timed(db.query_bow, w, v, k=10)[0] for w, v in bows]
            full = np.mean([sum(db._postings[w].n for w in ws.tolist() if w in db._postings) for ws, _ in bows])
            visited = full if db.max_postings is None else min(full, db.max_postings)
            stored = [(q, p) for q, p in zip(queries, picks) if p < len(db)]  # views the database holds
            recall = np.mean([abs(db.query(q, k=1)[0][0] - p) <= 2 for q, p in stored])
            print(f"{size:>9} {db.max_postings or 'full':>7} {1e3 * np.median(q_times):>10.2f} / "
                  f"{1e3 * np.percentile(q_times, 95):>8.2f} {1e3 * np.median(s_times):>11.2f} "
                  f"{1e3 * np.median(add_times[-100:]):>7.2f} {visited:>9.0f} {recall:>8.2f}")
        db.max_postings = budget

if __name__ == "__main__":
    main()
