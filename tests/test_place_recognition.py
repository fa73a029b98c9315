"""Place recognition: vocabulary tree, TF-IDF bags of words, the keyframe database (against ground truth)."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit import open_source
from slamkit.errors import ConfigError
from slamkit.features import create_extractor
from slamkit.place_recognition import PlaceDatabase, Vocabulary, VocabularyConfig, default_vocabulary
from slamkit.sources.scene import ROOM_Y


@pytest.fixture(scope="module")
def orb():
    return create_extractor("orb", num_features=1000)


@pytest.fixture(scope="module")
def vocabulary(orb):
    """Trained on a different synthetic sequence than the one queried (no test image is a training image)."""
    train = open_source("synthetic:handheld?frames=16&seed=3")
    return Vocabulary.train([orb.extract(f.gray).descriptors for f in train], VocabularyConfig(branching=8, depth=4))


@pytest.fixture(scope="module")
def default_seq():
    return open_source("default")


def _gaze_on_wall(pose: np.ndarray) -> np.ndarray:
    """(x, z) where the optical axis of a camera-to-world pose meets the front wall y = ROOM_Y (metres)."""
    c, z = pose[:3, 3], pose[:3, 2]
    p = c + (ROOM_Y - c[1]) / z[1] * z
    return p[[0, 2]]


def test_vocabulary_tree_shape_and_quantisation(vocabulary, orb, default_seq):
    assert vocabulary.kind == "binary" and vocabulary.descriptor_size == 32
    assert 8 ** 3 < vocabulary.num_words <= 8 ** 4
    assert np.all(vocabulary.idf >= 0)
    d = orb.extract(default_seq[10].gray).descriptors
    words = vocabulary.transform(d)
    assert words.shape == (len(d),) and words.min() >= 0 and words.max() < vocabulary.num_words
    # a descriptor is near the centre of its word: far nearer than to a random word's centre
    centre_of_word = vocabulary.centers[np.argsort(vocabulary.node_word)[-vocabulary.num_words:]]
    bits = np.unpackbits(d, axis=1)
    own = (bits != np.unpackbits(centre_of_word[words], axis=1)).sum(1)
    other = (bits != np.unpackbits(centre_of_word[np.random.default_rng(0).integers(0, len(centre_of_word),
                                                                                      len(d))], axis=1)).sum(1)
    assert own.mean() < 0.6 * other.mean()
    ids, w = vocabulary.bow(d)
    assert np.all(np.diff(ids) > 0) and np.all(w > 0) and w.sum() == pytest.approx(1.0, abs=1e-5)


def test_training_is_deterministic(orb, default_seq):
    descs = [orb.extract(default_seq[i].gray).descriptors for i in (0, 90, 180)]
    a = Vocabulary.train(descs, VocabularyConfig(branching=6, depth=2, seed=5))
    b = Vocabulary.train(descs, VocabularyConfig(branching=6, depth=2, seed=5))
    np.testing.assert_array_equal(a.centers, b.centers)
    np.testing.assert_array_equal(a.idf, b.idf)


def test_revisit_is_top_result_against_unrelated_frames(vocabulary, orb, default_seq):
    """The default sequence is a closed loop: its last frames see the wall of its first frames again."""
    gt = default_seq.gt_poses
    query = 356
    gaze = np.array([_gaze_on_wall(p) for p in gt])
    # the revisit: among the first 20 frames, the one nearest the query's pose (ground truth)
    revisit = int(np.argmin(np.linalg.norm(gt[:20, :3, 3] - gt[query, :3, 3], axis=1)))
    assert np.linalg.norm(gt[revisit, :3, 3] - gt[query, :3, 3]) < 0.1
    # unrelated: looking at a part of the wall 1.8 m or more away (the image spans about 3.6 m of it)
    unrelated = [i for i in range(30, 320, 6) if np.linalg.norm(gaze[i] - gaze[query]) > 1.8]
    assert len(unrelated) > 20
    db = PlaceDatabase(vocabulary)
    for i in [revisit] + unrelated:
        db.add(i, orb.extract(default_seq[i].gray).descriptors)
    hits = db.query(orb.extract(default_seq[query].gray).descriptors, k=5)
    assert hits[0][0] == revisit
    assert hits[0][1] > 1.2 * hits[1][1]
    # excluded keyframes are not returned
    assert revisit not in [i for i, _ in db.query(orb.extract(default_seq[query].gray).descriptors, k=5,
                                                  exclude={revisit})]


def test_identical_descriptors_score_maximum(vocabulary, orb, default_seq):
    db = PlaceDatabase(vocabulary)
    descs = {i: orb.extract(default_seq[i].gray).descriptors for i in (0, 60, 120, 240)}
    for i, d in descs.items():
        db.add(i, d)
    for i, d in descs.items():
        hits = db.query(d, k=4)
        assert hits[0][0] == i and hits[0][1] == pytest.approx(1.0, abs=1e-5)
        assert all(s < hits[0][1] - 0.05 for _, s in hits[1:])
        assert db.score(i, i) == pytest.approx(1.0, abs=1e-5)
    assert db.score(0, 120) == pytest.approx(dict(db.query(descs[0], k=4))[120], abs=1e-6)


def test_query_budget_keeps_the_rarest_words(vocabulary, orb, default_seq):
    """With a budget far below the postings a query would visit, the query is scored on its rarest words
    only: partial scores (below the full ones), and the same frame still comes first."""
    frames = list(range(0, 360, 12))
    descs = {i: orb.extract(default_seq[i].gray).descriptors for i in frames}
    full, budget = PlaceDatabase(vocabulary, max_postings=None), PlaceDatabase(vocabulary, max_postings=300)
    for i, d in descs.items():
        full.add(i, d)
        budget.add(i, d)
    words, _ = vocabulary.bow(descs[96])
    assert sum(full._postings[w].n for w in words.tolist()) > 10 * 300
    a, b = full.query(descs[96], k=3), budget.query(descs[96], k=3)
    assert a[0][0] == b[0][0] == 96
    assert b[0][1] < 0.5 * a[0][1]
    with pytest.raises(ConfigError, match="max_postings"):
        PlaceDatabase(vocabulary, max_postings=0)


def test_remove_and_arrays_round_trip(vocabulary, orb, default_seq, tmp_path):
    descs = {i: orb.extract(default_seq[i].gray).descriptors for i in (0, 30, 200, 250)}
    db = PlaceDatabase(vocabulary)
    for i, d in descs.items():
        db.add(i, d)
    db.remove(30)
    assert 30 not in db and len(db) == 3
    assert 30 not in [i for i, _ in db.query(descs[30], k=10)]
    with pytest.raises(KeyError):
        db.remove(30)
    db.add(77, descs[30])  # reuses the freed slot
    assert db.query(descs[30], k=1)[0][0] == 77
    np.savez(tmp_path / "db.npz", **db.to_arrays())
    with np.load(tmp_path / "db.npz", allow_pickle=False) as arrays:
        back = PlaceDatabase.from_arrays(arrays)
    assert back.image_ids == [0, 77, 200, 250] and back.max_postings == db.max_postings
    for d in descs.values():
        got, want = back.query(d, k=4), db.query(d, k=4)
        assert [i for i, _ in got] == [i for i, _ in want]
        np.testing.assert_allclose([s for _, s in got], [s for _, s in want], rtol=1e-6)
    np.testing.assert_array_equal(back.vocabulary.centers, vocabulary.centers)


def test_float_descriptors_use_kmeans_words(default_seq):
    sift = create_extractor("sift", num_features=500)
    descs = {i: sift.extract(default_seq[i].gray).descriptors for i in (0, 100, 200, 300)}
    voc = Vocabulary.train(list(descs.values()), VocabularyConfig(branching=6, depth=3))
    assert voc.kind == "float" and voc.descriptor_size == 128
    db = PlaceDatabase(voc)
    for i, d in descs.items():
        db.add(i, d)
    (best, score), = db.query(descs[200], k=1)
    assert best == 200 and score == pytest.approx(1.0, abs=1e-5)


def test_bad_descriptors_and_arguments(vocabulary):
    db = PlaceDatabase(vocabulary)
    with pytest.raises(ConfigError, match="dtype int32"):
        db.add(1, np.zeros((5, 32), np.int32))
    with pytest.raises(ConfigError, match="do not fit"):
        db.add(1, np.zeros((5, 64), np.uint8))
    with pytest.raises(ConfigError, match="do not fit"):
        db.add(1, np.zeros((5, 32), np.float32))
    with pytest.raises(ConfigError, match="image_id"):
        db.add(-1, np.zeros((5, 32), np.uint8))
    with pytest.raises(ConfigError, match="k must"):
        db.query(np.zeros((5, 32), np.uint8), k=0)
    with pytest.raises(ConfigError, match="branching"):
        VocabularyConfig(branching=1)
    with pytest.raises(ConfigError, match="missing"):
        PlaceDatabase.from_arrays({})
    assert db.query(np.zeros((0, 32), np.uint8)) == []


def test_default_vocabulary_is_cached(tmp_path, monkeypatch):
    """Trained on the embedded room on first use, then read back from the cache folder (same arrays)."""
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path))
    cfg = VocabularyConfig(branching=4, depth=2)
    first = default_vocabulary("orb", cfg, stride=90)
    files = list(tmp_path.glob("vocabulary-*.npz"))
    assert len(files) == 1
    second = default_vocabulary("orb", cfg, stride=90)
    np.testing.assert_array_equal(first.centers, second.centers)
    np.testing.assert_array_equal(first.idf, second.idf)
