"""What a screen costs against the graft it screens for: REPORT.md's per-encoder cost
table on planted seconds, and the extraction runtime a cell's record names."""

from __future__ import annotations

from bench.grid.kinds import GRAFT, SHORT_GRAFT
from bench.report.screen_cost import cost_table
from bench.screen.records import ScreenConditions, ScreenScores, new_screen_record
from tests.factories import make_record

CONDITIONS = ScreenConditions("h", "f", "fp16")
# encoder -> (screen s, extraction s, graft s per seed): ratios 2%, 4%, 10% (the worst), 1%.
PLANTED = {"alpha": (0.4, 100.0, (20.0, 20.0)), "beta": (1.0, 50.0, (24.0, 26.0)),
           "gamma": (3.0, 10.0, (30.0, 30.0)), "delta": (0.2, 0.0, (19.0, 21.0))}


def _rows(text: str) -> dict[str, list[str]]:
    """{encoder cell: the row's cells} of the table's smolvla rows."""
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in text.splitlines()
            if line.startswith("| smolvla")]
    return {r[2]: r for r in rows}


def _planted():
    stored = [new_screen_record(ScreenScores(e, "smolvla", "spatial", seconds=s), CONDITIONS,
                                0.01, extraction_seconds=x)
              for e, (s, x, _) in PLANTED.items()]
    records = [make_record(kind=GRAFT, encoder=e, seed=seed, timings_s={"total": t})
               for e, (_, _, grafts) in PLANTED.items() for seed, t in enumerate(grafts)]
    records += [make_record(kind=SHORT_GRAFT, encoder="alpha", variant=v, seed=0,
                            timings_s={"total": t}) for v, t in (("1_8", 3.0), ("1_4", 6.0))]
    return stored, records


def test_the_cost_table_shows_each_encoders_ratio_and_the_worst():
    stored, records = _planted()
    rows = _rows(cost_table(stored, records))
    assert set(rows) == set(PLANTED) | {"**mean of 4**"}
    assert rows["beta"][3:] == ["1", "50", "no record", "no record", "25", "4.0%"]
    assert rows["alpha"][3:] == ["0.4", "100", "3", "6", "20", "2.0%"]
    assert rows["gamma"][-1] == "10.0%" and rows["delta"][-1] == "1.0%"
    summary = rows["**mean of 4**"]
    # means over the encoders: screen (0.4 + 1 + 3 + 0.2) / 4, graft (20 + 25 + 30 + 20) / 4,
    # ratio (2 + 4 + 10 + 1) / 4 %; the short grafts over the one encoder that has them.
    assert summary[3:] == ["1.15", "40", "3", "6", "23.8", "4.2%; worst 10.0% (gamma)"]


def test_an_encoder_without_a_graft_has_no_ratio_and_is_never_the_worst():
    stored, records = _planted()
    records = [r for r in records if not (r.encoder == "gamma" and r.kind == GRAFT)]
    rows = _rows(cost_table(stored, records))
    assert rows["gamma"][-2:] == ["no graft record", "n/a"]
    assert rows["**mean of 4**"][-1] == "2.3%; worst 4.0% (beta)"


def test_the_cost_table_counts_the_extraction_a_screen_found_stored():
    """A screen that opened the graft's stored features spent 0.017 s; the file took 300 s to
    extract. The table showed 0.017: the screen looked free. A record from before
    extraction_seconds counts its own feature seconds."""
    stored = [new_screen_record(ScreenScores("dinov2_s", "smolvla", "spatial", seconds=0.5),
                                CONDITIONS, 0.017, extraction_seconds=300.0),
              new_screen_record(ScreenScores("pixels", "smolvla", "spatial", seconds=0.5),
                                CONDITIONS, 2.0)]
    rows = _rows(cost_table(stored, []))
    assert rows["dinov2_s"][3:5] == ["0.5", "300"] and rows["pixels"][3:5] == ["0.5", "2"]
    assert rows["**mean of 2**"][3:5] == ["0.5", "151"]  # (300 + 2) / 2


def test_the_store_names_the_runtime_that_extracted_it(tmp_path, monkeypatch):
    """What a store's views say extracted them: torch; another runtime's tag when it extracted
    (also when the file is found built: no export then); torch when its export failed (the
    fallback). Arrays in memory say nothing. The export itself: tests/test_extraction_runtime."""
    import torch

    from bench.resources import extraction
    from bench.resources.features import FeatureStore, feature_runtime
    from bench.loops.encode import encode_grid
    from encoders import build_encoder
    from tests.test_features import FakeSuite

    encoder, exports = build_encoder("pixels", "tiny"), []

    def views(root, runtime, export_works=True):
        store = FeatureStore(root, dtype="float32", progress=False, chunk_frames=2,
                             runtime=runtime)
        # A planted runtime: its "export" is torch's forward, counted.
        monkeypatch.setattr(store, "_run", lambda enc, suite: exports.append(root) or (
            (lambda images: encode_grid(enc, images)) if export_works else None))
        return store.pooled_features(encoder, FakeSuite(n_frames=2), (2, 2))

    assert feature_runtime(views(tmp_path / "t", "torch")) == "torch" and not exports
    monkeypatch.setattr(extraction, "planned_tag", lambda enc, runtime: "ort==test/opset17")
    assert feature_runtime(views(tmp_path / "o", "onnxruntime")) == "ort==test/opset17"
    assert feature_runtime(views(tmp_path / "o", "onnxruntime")) == "ort==test/opset17"
    assert exports == [tmp_path / "o"]  # found built the second time: no export
    assert feature_runtime(views(tmp_path / "f", "onnxruntime", export_works=False)) == "torch"
    assert feature_runtime({"cam": torch.zeros(2, 4, 8)}) is None
    assert feature_runtime(None) is None


def test_a_record_keeps_the_runtime_and_older_records_read_as_they_were():
    from bench.results.record import Record

    tag = "onnxruntime==1.31.1/opset17"
    record = make_record(features_mode="cache", feature_runtime=tag)
    assert record.to_json()["feature_runtime"] == tag
    assert Record.from_json(record.to_json()).measured.feature_runtime == tag
    older = make_record(features_mode="cache").to_json()  # a record from before the field
    assert "feature_runtime" not in older
    assert Record.from_json(older).measured.feature_runtime is None
    assert Record.from_json(older).to_json() == older  # read and written back bit for bit


def test_a_screen_record_keeps_the_runtime_and_older_ones_read_without_it():
    from bench.screen.records import ScreenRecord

    made = new_screen_record(ScreenScores("effnet_lite0", "smolvla", "spatial", seconds=1.0),
                             CONDITIONS, 0.1, 200.0, "torch")
    assert ScreenRecord.from_json(made.to_json()).extraction_runtime == "torch"
    older = {k: v for k, v in made.to_json().items() if k != "extraction_runtime"}
    assert ScreenRecord.from_json(older).extraction_runtime is None


def test_provenance_lists_the_runtime_per_encoder():
    from bench.report.provenance import extraction_runtimes

    tag = "onnxruntime==1.31.1/opset17"
    records = [make_record(encoder="effnet_lite0", features_mode="cache", feature_runtime=tag),
               make_record(encoder="effnet_lite0", seed=1, features_mode="cache",
                           feature_runtime=tag),
               make_record(encoder="dinov2_s", features_mode="cache", feature_runtime="torch"),
               make_record(encoder="pixels", features_mode="cache"),  # from before the field
               make_record(encoder="siglip", features_mode="loop")]  # no store read
    screens = [new_screen_record(ScreenScores("fastvit", "smolvla", "spatial"), CONDITIONS, 0.1,
                                 extraction_runtime="torch")]
    assert extraction_runtimes(records, screens) == (
        "Feature extraction runtime per encoder (bench.resources.extraction): dinov2_s: torch; "
        f"effnet_lite0: {tag}; fastvit: torch; pixels: not recorded")
    assert extraction_runtimes(records[3:], []) is None  # no record names one: no line


def _small_world(tmp_path):
    """(stored fp16 file of 2 cameras x 60 frames x 2x2 tokens x 3 channels, suite, split,
    backbone): what a screen reads, small and fake (12 channels' worth of numbers, not a task)."""
    from types import SimpleNamespace

    import torch

    from bench.resources import feature_file as fs

    frames, cameras = 60, ("cam0", "cam1")
    layout = fs.Layout("k", cameras, frames, (2, 2), 3, "fp16")
    gen = torch.Generator().manual_seed(0)
    stored = fs.build(tmp_path / "k.feat", layout, lambda a, b: {
        c: torch.rand(b - a, 4, 3, generator=gen) for c in cameras}, 20)
    suite = SimpleNamespace(state=torch.randn(frames, 8, generator=gen),
                            action=torch.randn(frames, 7, generator=gen),
                            episode_index=torch.arange(frames) // 10)
    split = SimpleNamespace(train_frames=torch.arange(40), train_episodes=[0, 1, 2, 3],
                            windows=torch.arange(40, 60, 2))
    backbone = SimpleNamespace(info=SimpleNamespace(native_grid=(1, 1), chunk_size=4),
                               normalize_actions=lambda a: a)
    return stored, suite, split, backbone


def test_a_screen_names_the_runtime_of_the_store_it_read(tmp_path):
    """measure_screen keeps the runtime its views say extracted them, with the file's build
    seconds (a fake workspace: the screen's own numbers are not checked here)."""
    from types import SimpleNamespace

    from bench.resources.features import PooledView
    from bench.screen.measure import measure_screen

    stored, suite, split, backbone = _small_world(tmp_path)
    import torch

    encoder = torch.nn.Conv2d(3, 3, 4, stride=4)  # what the naive baselines count
    encoder.input_size = 8
    ws = SimpleNamespace(backbone=lambda b, s: backbone, suite=lambda s: suite,
                         split=lambda s: split,
                         features=lambda e, s, grid: {c: PooledView(stored, c, grid,
                                                                    runtime="ort==t/opset17")
                                                      for c in stored.layout.cameras},
                         encoder=lambda e: encoder)
    record = measure_screen(ws, "enc", "smolvla", "spatial", CONDITIONS)
    assert record.scores.score("resolution") == 8.0
    assert record.scores.score("param_count") == 3 * 3 * 16 + 3
    assert record.extraction_runtime == "ort==t/opset17"
    assert record.extraction_seconds == stored.manifest["build_s"]


def test_a_screens_bits_do_not_depend_on_how_many_windows_it_reads_at_once(tmp_path,
                                                                           monkeypatch):
    """measure.CHUNK (64: a batch that stays in the caches) against the whole split at once:
    every step from the stored grid to the proxies is per window, so the same bits."""
    from bench.resources.features import PooledView
    from bench.screen import measure

    stored, suite, split, backbone = _small_world(tmp_path)
    views = {c: PooledView(stored, c, (2, 1)) for c in stored.layout.cameras}

    def scores():
        out = measure.screen_features(views, suite, split, backbone.normalize_actions, 4,
                                      ("enc", "smolvla", "spatial")).to_json()
        out.pop("seconds")
        return out

    monkeypatch.setattr(measure, "CHUNK", 2048)
    whole = scores()
    monkeypatch.setattr(measure, "CHUNK", 7)
    assert scores() == whole
