import json

import pytest

from bench.results.current import RunConditions
from bench.results.store import ResultStore, ResultsDirError, atomic_write_json, load_failure
from tests.factories import make_failed, make_record

C1 = "smolvla-spatial-dinov2_s-seed0"


def test_write_load_and_resume_by_protocol_hash(tmp_path):
    store = ResultStore(tmp_path)
    store.write(make_record(per_window=[1.0, 1.0], protocol_hash="aaa"))
    assert store.current(C1, RunConditions(protocol_hash="aaa")).mse_in() == 1.0
    assert store.current(C1, RunConditions(protocol_hash="bbb")) is None  # other protocol
    assert store.current("c2", RunConditions(protocol_hash="aaa")) is None


def test_failure_never_counts_as_done_and_is_cleared_by_success(tmp_path):
    store = ResultStore(tmp_path)
    store.write_failure(make_failed(error="boom"))
    assert store.load(C1) is None and load_failure(tmp_path, C1).error == "boom"
    assert (tmp_path / "failed" / f"{C1}.json").exists()
    store.write(make_record())
    assert not (tmp_path / "failed" / f"{C1}.json").exists()


def test_atomic_write_leaves_old_file_on_crash(tmp_path):
    path = tmp_path / "r.json"
    atomic_write_json(path, {"a": 1})
    with pytest.raises(TypeError):
        atomic_write_json(path, {"a": object()})  # not serialisable: fails mid-write
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temp file left behind


def test_corrupt_record_is_treated_as_missing(tmp_path):
    store = ResultStore(tmp_path)
    store.cell_path(C1).write_text("{half a rec")
    assert store.load(C1) is None


def test_results_dir_that_is_a_file_is_a_clear_error(tmp_path):
    blocker = tmp_path / "results"
    blocker.write_text("not a folder")
    with pytest.raises(ResultsDirError, match=r"not writable.*--results-dir"):
        ResultStore(blocker)


def test_stores_opened_at_once_on_one_folder_do_not_trip_each_other(tmp_path):
    """xdist workers and the controller open the same results dir at the same moment."""
    from concurrent.futures import ThreadPoolExecutor

    def open_many(_):
        for _ in range(200):
            ResultStore(tmp_path / "shared")

    with ThreadPoolExecutor(8) as pool:
        list(pool.map(open_many, range(8)))  # re-raises a ResultsDirError from any thread
    assert not list((tmp_path / "shared").glob(".write-probe*"))


def test_a_slice_adds_to_the_folders_grid_and_drops_only_what_it_no_longer_expects(tmp_path):
    """A -k slice under --screen lists its cells at start-up, then at its end without the ones
    the screen dropped; another slice's cells stay expected."""
    store = ResultStore(tmp_path)
    store.write_grid(["a-1", "a-2"], "tiny")
    store.write_grid(["b-1", "b-2"], "tiny", add=True)  # the slice's start-up
    store.write_grid(["b-1"], "tiny", add=True, drop={"b-2"})  # its end: b-2 screened out
    assert json.loads((tmp_path / "grid.json").read_text())["expected"] == ["a-1", "a-2", "b-1"]
    store.write_grid(["c-1"], "sim", add=True)  # another profile's slice redefines it
    assert json.loads((tmp_path / "grid.json").read_text())["expected"] == ["c-1"]
