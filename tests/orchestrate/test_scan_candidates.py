"""Which catalogue assets a scan checks for a suspect, and in what order."""

from pipeline.orchestrate.candidates import candidates as _candidates
from pipeline.orchestrate.candidates import after_whole, cascade


def _info(shape, distances, votes):
    return {"ranking": shape, "distances": distances, "index_ranking": votes}


def test_rankings_alternate_best_first_without_repeats():
    info = _info(["a", "b", "c", "d"], [0.01, 0.5, 0.6, 0.7], ["x", "a", "y", "z"])
    assert _candidates(info, set("abcdxyz"), 3, 1.6) == ["a", "x", "b", "c", "y"]


def test_near_ties_in_shape_are_added_up_to_twice_top_k():
    names = [f"s{i}" for i in range(10)]
    info = _info(names, [0.10, 0.11, 0.12, 0.13, 0.15, 0.16, 0.17, 0.5, 0.6, 0.7], [])
    assert _candidates(info, set(names), 3, shape_margin=1.6) == names[:6]
    assert _candidates(info, set(names), 3, shape_margin=1.35) == names[:4]
    assert _candidates(info, set(names), 3, shape_margin=1.0) == names[:3]


def test_only_assets_in_view_are_candidates_and_the_margin_counts_from_the_nearest_in_view():
    info = _info(["gone", "a", "b", "c", "d"], [0.0, 0.10, 0.12, 0.14, 0.15], ["gone", "b"])
    assert _candidates(info, {"a", "b", "c", "d"}, 2, shape_margin=1.6) == ["a", "b", "c", "d"]
    assert "gone" not in _candidates(info, {"a", "b"}, 2, 1.6)


def test_the_cascade_sends_voted_or_near_candidates_deep_nearish_ones_quick_and_stops_the_rest():
    info = {"index_ranking": ["x", "a", "b", "c", "d", "e"], "index_votes": [float("inf"), 0.31, 0.02, -0.01, 0, 0.5],
            "ranking": ["c", "b", "a", "d", "x", "e"], "distances": [0.01, 0.04, 0.2, 0.3, 0.5, 0.9]}
    picked = ["a", "b", "c", "d", "e", "x"]
    assert cascade(info, picked, 0.1, 0.02, 0.25) == {"a": "deep", "b": "quick", "c": "deep", "d": None,
                                                      "e": "deep", "x": "deep"}
    assert cascade(info, picked, 0.4, 0.05, 0.35) == {"a": "quick", "b": "deep", "c": "deep", "d": "quick",
                                                      "e": "deep", "x": "deep"}
    assert cascade(info, picked, 1.0, 0.0, 0.1) == {"a": None, "b": "quick", "c": "quick", "d": None, "e": None,
                                                    "x": "deep"}
    assert cascade(info, picked, None, 0.0, 0.0) == dict.fromkeys(picked, "deep")       # the cascade off
    assert cascade(info, picked, 1.0, 0.0, None) == {**dict.fromkeys(picked, "quick"), "x": "deep"}
    assert cascade(info, ["f"], 1.0, 0.0, 0.0) == {"f": "deep"}        # neither indexed nor ranked: deep
    assert cascade({}, ["a"], 1.0, 0.0, 0.0) == {"a": "deep"}          # no index: deep


def test_a_candidate_takes_the_votes_of_its_twins_and_no_one_else_s():
    # the ratio test splits votes between one shape sampled twice: "b" is "a" at another sampling
    info = {"index_ranking": ["a", "b", "c"], "index_votes": [0.17, 0.001, 0.2],
            "ranking": ["a", "b", "c"], "distances": [0.09, 0.09, 0.4], "twins": {"a": [["b", 0.029]], "c": []}}
    assert cascade(info, ["a", "b", "c"], 0.03, 0.05, None) == dict.fromkeys("abc", "deep")
    assert cascade({**info, "twins": {}}, ["a", "b", "c"], 0.03, 0.05, None) == {"a": "deep", "b": "quick", "c": "deep"}
    # a twin lends the votes it has, not more
    low = {**info, "index_votes": [0.02, 0.001, 0.2]}
    assert cascade(low, ["b"], 0.03, 0.05, None) == {"b": "quick"}


def test_a_suspect_laid_whole_on_one_original_keeps_twins_and_whole_look_alikes_quick_and_holders_of_it_as_they_were():
    # "w" laid it whole: "t" is its twin; "n" looks like it whole, "q" too but held to the quick steps;
    # "c" has a cut view like it (a part of "c" may be it); "h" is far in shape but draws the votes
    # once "w" is left out (a scene holding "w")
    info = {"ranking": ["w", "n", "q", "c", "t", "h", "far", "farther"],
            "distances": [0.0, 0.05, 0.06, 0.04, 0.2, 0.25, 0.3, 0.4],
            "whole_distances": [0.0, 0.05, 0.06, 0.3, 0.2, 0.5, 0.3, 0.4],
            "twins": {"w": [["t", 0.028]], "far": [["farther", 0.01]]}}
    stages = {"n": "deep", "q": "quick", "c": "deep", "t": "deep", "h": "deep", "far": "deep", "farther": "deep"}
    few = {"n": 0.0, "q": 0.0, "c": 0.0, "t": 0.5, "h": 0.04, "far": 0.01, "farther": -0.02}
    assert after_whole(info, stages, "w", 0.03, 0.06, few) == {
        "n": "quick", "q": "quick", "c": "deep", "t": "quick", "h": "deep", "far": None, "farther": None}
    # votes keep any stage but a twin's; a stopped one stays stopped
    assert after_whole(info, stages, "w", 0.03, 0.06, {**few, "n": 0.2, "far": 0.05})["n"] == "deep"
    assert after_whole(info, stages, "w", 0.03, 0.06, {**few, "far": 0.05})["far"] == "deep"
    assert after_whole(info, {**stages, "c": None}, "w", 0.03, 0.06, few)["c"] is None
    # another's twins are not its twins; an asset without votes (not indexed) goes on as it was
    assert after_whole(info, stages, "far", 0.03, 0.06, few)["farther"] == "quick"
    assert after_whole(info, stages, "far", 0.03, 0.06, few)["t"] == "deep"
    assert after_whole(info, stages, "w", 0.03, 0.06, {})["far"] == "deep"
    # the cascade off, or the votes unknown: every stage kept
    assert after_whole(info, stages, "w", None, 0.06, few) == stages
    assert after_whole(info, stages, "w", 0.03, None, few) == stages
    assert after_whole(info, stages, "w", 0.03, 0.06, None) == stages


def test_what_earlier_copies_laid_whole_witnessed_decides_before_the_votes_and_twins_stay_quick():
    info = {"ranking": ["w", "n", "c", "t", "h", "far"], "distances": [0.0, 0.05, 0.04, 0.2, 0.25, 0.3],
            "whole_distances": [0.0, 0.05, 0.3, 0.2, 0.5, 0.3], "twins": {"w": [["t", 0.028]]}}
    stages = {"n": "deep", "c": "deep", "t": "deep", "h": "deep", "far": "deep"}
    few = {"n": 0.0, "c": 0.0, "t": 0.5, "h": 0.04, "far": 0.01}
    before = after_whole(info, stages, "w", 0.03, 0.06, few)
    assert before == {"n": "quick", "c": "deep", "t": "quick", "h": "deep", "far": None}
    # lay on nowhere: not registered, votes or cut views notwithstanding; lay on: kept as the cascade had it
    held = {"c": False, "h": False, "far": True, "n": None, "t": False}
    assert after_whole(info, stages, "w", 0.03, 0.06, few, held) == {
        "n": "quick", "c": None, "t": "quick", "h": None, "far": "deep"}
    # not ranked, every one witnessed ({}): twins quick, then the witnesses; one not witnessed goes on
    assert after_whole(info, stages, "w", 0.03, 0.06, {}, held) == {
        "n": "deep", "c": None, "t": "quick", "h": None, "far": "deep"}
    # the votes unknown (the ranking failed): the witnesses alone, a twin's stage kept unless one decides it
    assert after_whole(info, stages, "w", 0.03, 0.06, None, held) == {
        "n": "deep", "c": None, "t": None, "h": None, "far": "deep"}
    assert after_whole(info, stages, "w", 0.03, 0.06, None, {}) == stages
    # the cascade off: nothing stopped, whatever was witnessed
    assert after_whole(info, stages, "w", None, 0.06, few, held) == stages


def _check(*fits, lies_on=None, shas=None):
    shas = shas or ["b" * 64] * len(fits)
    return {"asset_key": "b", "groups": [{"registration": {"fitness": f, "lies_on": lies_on}, "original_sha256": sha}
                                         for f, sha in zip(fits, shas)]}


def test_a_check_witnesses_per_original_holding_by_fitness_and_surface_and_nowhere_only_when_it_went_deep():
    from pipeline.orchestrate.candidates import HOLD_FIT, held_by, holding_of

    b, c = "b" * 64, "c" * 64
    assert holding_of(_check(0.2, HOLD_FIT), deep=False) == {b: True}          # any registration that lay on it
    assert holding_of(_check(0.2, HOLD_FIT, lies_on=True), deep=False) == {b: True}
    assert holding_of(_check(0.2, 0.3), deep=True) == {b: False}
    assert holding_of(_check(0.2, 0.3), deep=False) == {}                       # the quick steps alone: nothing
    assert holding_of(_check(), deep=True) == {}                                # nothing registered
    # near the original, but off its surface (a sparse original's wide band): on it nowhere
    assert holding_of(_check(0.99, lies_on=False), deep=True) == {b: False}
    # an asset's two originals (a revision) are witnessed apart
    assert holding_of(_check(0.2, 0.9, shas=[b, c]), deep=True) == {b: False, c: True}
    assert held_by([], 1.0) is None and held_by(None, 1.0) is None
    assert held_by([{"held": False, "sampling": 1.0}, {"held": False, "sampling": 1.1}], 1.0) is False
    assert held_by([{"held": False, "sampling": 1.0}, {"held": True}], 1.0) is True   # one that lay on it is enough
    assert held_by([{"held": True}], None) is True
    assert held_by([{"held": False, "sampling": 1.0}, {"held": "no"}], 1.0) is None   # a record not understood
    assert held_by([{"held": False, "sampling": 1.0}, ["x"]], 1.0) is None
    # a sparser copy is judged more leniently: a denser witness's "nowhere" does not speak for it
    assert held_by([{"held": False, "sampling": 1.0}], 3.0) is None
    assert held_by([{"held": False, "sampling": 1.0}, {"held": False, "sampling": 3.2}], 3.0) is False
    assert held_by([{"held": False, "sampling": 3.0}], 1.0) is False
    assert held_by([{"held": False, "sampling": None}], 1.0) is None
    assert held_by([{"held": False, "sampling": 1.0}], None) is None


def test_witnesses_are_kept_per_pair_of_originals_and_settings_never_replaced_and_read_back(tmp_path):
    from types import SimpleNamespace

    from pipeline.config import DetectParams
    from pipeline.io.basis_store import read_holdings
    from pipeline.orchestrate.candidates import holdings, witness, witness_settings

    whole = {"asset_key": "w", "sha256": "a" * 64, "sampling": 1.0}
    b, c = "b" * 64, "c" * 64
    settings = witness_settings(DetectParams(registration="robust"))
    assert witness_settings(SimpleNamespace(registration="paper")) is None
    # what a deep check can find depends on the search screen: with it off, other witnesses
    assert witness_settings(DetectParams(registration="robust", search_screen=False)) not in (settings, None)
    assert holdings(tmp_path, whole, {"b": {b}}, settings) == {"b": None}
    assert witness(tmp_path, whole, _check(0.1), True, "1" * 64, settings) == {b: False}
    assert holdings(tmp_path, whole, {"b": {b}}, settings) == {"b": False}
    assert holdings(tmp_path, {**whole, "sampling": 2.0}, {"b": {b}}, settings) == {"b": None}   # a sparser suspect
    # the asset revised: its new original has no witness, so the asset is not decided
    assert holdings(tmp_path, whole, {"b": {b, c}}, settings) == {"b": None}
    # the same witness again, now saying otherwise: the first record stands
    assert witness(tmp_path, whole, _check(0.9), True, "1" * 64, settings) == {b: True}
    assert holdings(tmp_path, whole, {"b": {b}}, settings) == {"b": False}
    # another witness that lay on it: held; neither record is replaced
    witness(tmp_path, whole, _check(0.9), True, "2" * 64, settings)
    assert holdings(tmp_path, whole, {"b": {b}}, settings) == {"b": True}
    records = read_holdings(tmp_path, whole["sha256"], b, settings)
    assert sorted(r["held"] for r in records) == [False, True]
    assert {r["witness_sha256"] for r in records} == {"1" * 64, "2" * 64}
    assert {(r["whole_asset_key"], r["asset_key"], r["original_sha256"]) for r in records} == {("w", "b", b)}
    # the other way round, other settings, another whole original: no witness yet
    assert holdings(tmp_path, {**whole, "sha256": b}, {"w": {"a" * 64}}, settings) == {"w": None}
    assert holdings(tmp_path, whole, {"b": {b}}, "f" * 64 if settings[0] != "f" else "e" * 64) == {"b": None}
    assert holdings(tmp_path, {**whole, "sha256": "d" * 64}, {"b": {b}}, settings) == {"b": None}
    assert holdings(tmp_path, whole, {"b": {b}}, None) == {"b": None}
    assert witness(tmp_path, whole, _check(0.1), True, "3" * 64, None) == {b: False}       # nothing kept
    assert len(read_holdings(tmp_path, whole["sha256"], b, settings)) == 2
    # a record that cannot be parsed: unknown, never "lay on it nowhere"
    (next(tmp_path.glob("holdings/*/*/*.json")).parent / "4.json").write_text("{not json")
    assert holdings(tmp_path, whole, {"b": {b}}, settings) == {"b": None}


def test_the_index_is_kept_by_its_bytes_hash_and_a_changed_file_is_never_served_stale(tmp_path):
    import numpy as np
    import pytest

    from pipeline.features import FeatureIndex
    from pipeline.io.pointcloud import sha256_file
    from pipeline.orchestrate.candidates import load_index

    def index(keys):
        feats = np.eye(33, dtype=np.float32)[: len(keys)]
        return FeatureIndex(list(keys), feats, np.arange(len(keys), dtype=np.int32), ["h"] * len(keys),
                            np.zeros(len(keys)))

    path = tmp_path / "index.npz"
    index(["a", "b"]).save(path)
    sha = sha256_file(path)
    assert load_index(path, sha).keys == ["a", "b"]
    path.unlink()                                     # held by its hash: no read at all
    assert load_index(path, sha).keys == ["a", "b"]
    index(["a", "b", "c"]).save(path)                 # rebuilt at the same path
    assert load_index(path).keys == ["a", "b", "c"]
    with pytest.raises(ValueError, match="changed since the scan began"):
        load_index(path, "0" * 64)


def test_a_new_catalogue_version_grows_the_kept_index_and_a_changed_asset_rebuilds_it(tmp_path):
    import numpy as np

    from pipeline.demo import procedural_shape
    from pipeline.io.pointcloud import write_array
    from pipeline.orchestrate.candidates import build_index, load_index

    shapes = {"b": ("torus", 1), "c": ("shell", 2), "a": ("blob", 3)}
    paths = {k: write_array(tmp_path / "assets", k, procedural_shape(kind, 2000, seed=s) * 10, "ply")
             for k, (kind, s) in shapes.items()}
    first = build_index(tmp_path / "out", "v1", {k: paths[k] for k in "bc"})
    grown = build_index(tmp_path / "out", "v2", paths)             # "a" added: b and c are not described again
    fresh = build_index(tmp_path / "fresh", "v2", paths)
    one, two, new = load_index(first), load_index(grown), load_index(fresh)
    assert one.keys == ["b", "c"] and two.keys == ["b", "c", "a"] and new.keys == ["a", "b", "c"]
    assert two.sources == [new.sources[new.keys.index(k)] for k in two.keys]
    suspect = procedural_shape("blob", 2000, seed=3) * 10
    assert dict(two.rank(suspect, 3)) == dict(new.rank(suspect, 3))
    assert np.allclose(two.shape_distances(suspect)[[2, 0, 1]], new.shape_distances(suspect))
    # b's bytes change: the kept indexes no longer hold the catalogue, so v3 is described afresh
    write_array(tmp_path / "assets", "b", procedural_shape("torus", 2000, seed=9) * 10, "ply", keep_existing=False)
    assert load_index(build_index(tmp_path / "out", "v3", paths)).keys == ["a", "b", "c"]


def test_an_ivf_index_is_kept_in_two_files_searched_memory_mapped_and_checked_by_its_hash(tmp_path):
    import faiss
    import pytest

    from pipeline import features
    from pipeline.demo import procedural_shape
    from pipeline.io.basis_store import write_file
    from pipeline.orchestrate import candidates as cand

    clouds = {k: procedural_shape(kind, 2000, seed=s) * 10 for k, kind, s in
              (("a", "blob", 1), ("b", "torus", 2), ("c", "shell", 3))}
    index = features.build_index(clouds, ivf=True)
    npz, ivf = index.to_parts()
    write_file(tmp_path, "state/index-v6-x.ivf", ivf)
    path = write_file(tmp_path, "state/index-v6-x.npz", npz)
    mapped = cand.load_index(path)
    assert isinstance(faiss.downcast_InvertedLists(mapped.ivf.invlists), faiss.OnDiskInvertedLists)
    suspect = procedural_shape("torus", 2000, seed=2) * 10
    assert mapped.rank(suspect, 3) == index.rank(suspect, 3) and mapped.rank(suspect, 1)[0][0] == "b"
    with pytest.raises(ValueError, match="memory-mapped"):          # never faiss's abort
        mapped.extend({"d": procedural_shape("blob", 2000, seed=4)})
    cand._INDEXES.clear()
    (tmp_path / "state" / "index-v6-x.ivf").write_bytes(ivf[:-1] + bytes([ivf[-1] ^ 1]))
    with pytest.raises(ValueError, match="differs from what the index recorded"):
        cand.load_index(path)
    (tmp_path / "state" / "index-v6-x.ivf").unlink()
    with pytest.raises(ValueError, match="cannot be read"):
        cand.load_index(path)
