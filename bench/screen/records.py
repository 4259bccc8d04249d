"""The screen tier's stored forms, typed: the ONE place their keys are spelled (as field names).

    RESULTS_DIR/screens/<screen_id>.json             one screen: status "ok" (a ScreenRecord)
                                                     or "failed" (a ScreenFailure)
    RESULTS_DIR/screens/selections/<b>-<s>.json      what a --screen run grafted and dropped on
                                                     backbone b x suite s (a ScreenSelection),
                                                     and the calibration study it named

A screen id reads as the pytest case: `smolvla-spatial-timm:convnext_atto` (backbone-suite-encoder;
no seed: a screen trains nothing). bench.results.store reads and writes the files; a screen record
stands for a later run when `screen_conditions` match (protocol, normaliser, feature dtype,
screen version) and it holds every proxy of the table (bench.cell.screening). Undefined proxies
travel as {"undefined": reason}, never as NaN.

Where a proxy's values live (bench.screen.proxies says which kind each is): a supervised one's
under proxies[name] as {input set: value, "gain": score}; the label-free entropy in the field of
its own (the layout from before the table); any later label-free one under proxies[name] as
{"heldout": value, "gain": score}; a naive baseline (the encoder's cost) under proxies[name] as
{"value": value, "gain": score}.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import asdict, dataclass, field, fields

from bench.grid.cells import screen_id
from bench.screen.proxies import ENTROPY
from bench.stats import Measure, Undefined

# Bump when a proxy's definition changes: older screen records are then measured again.
# 2: LogME in the n - 1 centred dims, finite where D > N. 3: LogME's maximum by a bounded profile
# search (was a fixed point capped at 100,000 steps), ridge's errors from residuals, both in the
# cheaper of the D x D and N x N forms; scores within 1e-9 relative of 2's where 2 converged.
# 4: ridge's fold fits share all training windows' scales, each still penalised ratio * its own
# windows (exact grouped cross-validation through a full fit's hat matrix, no eigh per fold):
# its chosen penalty can move.
SCREEN_VERSION = 4
OK, FAILED = "ok", "failed"
_STATUS = "status"  # the envelope key; every other key is a field name
GAIN, HELDOUT = "gain", "heldout"  # a proxy's score; a label-free proxy's value (not entropy's)
VALUE = "value"  # a naive baseline's value (the encoder's cost: bench.screen.proxies ENCODER)


def _out(value: Measure):
    return {"undefined": value.reason} if isinstance(value, Undefined) else float(value)


def _in(value) -> Measure:
    return Undefined(value["undefined"]) if isinstance(value, dict) else float(value)


@dataclass
class ScreenScores:
    """One screen's proxies (where each lives: the module doc): per supervised proxy {input set:
    value} plus "gain"; entropy; sizes. Values are floats or bench.stats.Undefined (with the
    reason)."""

    encoder: str
    backbone: str
    suite: str
    proxies: dict = field(default_factory=dict)
    chosen: dict = field(default_factory=dict)  # per input set: ridge penalty, k (chooses=)
    entropy: Measure = Undefined("not computed")
    n_train: int = 0
    n_heldout: int = 0
    dims: dict = field(default_factory=dict)
    seconds: float = 0.0  # the screen's own solve, feature extraction not counted

    def to_json(self) -> dict:
        """JSON-ready, one key per field; an undefined value is {"undefined": reason}."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["proxies"] = {p: {k: _out(v) for k, v in vals.items()}
                          for p, vals in self.proxies.items()}
        out[ENTROPY] = _out(self.entropy)
        return out

    @classmethod
    def from_json(cls, data: dict) -> "ScreenScores":
        proxies = {p: {k: _in(v) for k, v in vals.items()} for p, vals in data["proxies"].items()}
        return cls(**{**data, "proxies": proxies, ENTROPY: _in(data[ENTROPY])})

    def value(self, proxy: str, key: str) -> Measure:
        """`proxy`'s value under `key`: an input set, GAIN or HELDOUT (entropy: its own field);
        Undefined, saying so, when this screen was measured before the proxy was registered."""
        if proxy == ENTROPY:
            return self.entropy
        if key not in self.proxies.get(proxy, {}):
            return Undefined(f"{proxy} {key}: not in this screen (measured before {proxy} was "
                             "added; a --screen run measures it again)")
        return self.proxies[proxy][key]

    def keep_label_free(self, proxy: str, value: Measure, score: Measure,
                        key: str = HELDOUT) -> None:
        """A label-free proxy's value (under `key`: HELDOUT, or VALUE for a naive baseline) and
        its score, where this layout keeps them."""
        if proxy == ENTROPY:
            self.entropy = value
        else:
            self.proxies[proxy] = {key: value, GAIN: score}

    def holds(self, proxy: str) -> bool:
        """Has this screen measured `proxy` (a screen stored before a proxy was added has not)?"""
        return proxy == ENTROPY or proxy in self.proxies

    def score(self, proxy: str) -> Measure:
        """The ranking score of `proxy`, higher is better (bench.screen.proxies: a supervised
        proxy's gain of the features over the state, a label-free one's value, oriented)."""
        return self.value(proxy, GAIN)


@dataclass(frozen=True)
class ScreenConditions:
    """What a screen was measured under; a stored screen resumes only when all match."""

    protocol_hash: str
    normalizer_fingerprint: str
    feature_dtype: str
    screen_version: int = SCREEN_VERSION


@dataclass(frozen=True)
class ScreenRecord:
    """A finished screen: its scores, what it was measured under, how long the features took."""

    scores: ScreenScores
    conditions: ScreenConditions
    feature_seconds: float = 0.0  # opening (on first use: extracting) the stored features
    created: str = ""
    # How long extracting the stored features took, whichever tier did it (the file's build_s):
    # a screen that found the graft's features stored spent ~0 s, yet they were not free.
    extraction_seconds: float | None = None
    # What extracted them (bench.resources.extraction): "torch" or an onnxruntime tag; None before it.
    extraction_runtime: str | None = None

    @property
    def screen_id(self) -> str:
        return screen_id(self.scores.backbone, self.scores.suite, self.scores.encoder)

    def to_json(self) -> dict:
        """{status: ok, scores: ScreenScores JSON, conditions: {...}, feature_seconds, created}."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        return {**out, _STATUS: OK, "scores": self.scores.to_json(),
                "conditions": asdict(self.conditions)}

    @classmethod
    def from_json(cls, data: dict) -> "ScreenRecord":
        """A validated record; ValueError naming the first problem."""
        if _status(data) != OK:
            raise ValueError(f"not a finished screen (status {_status(data)!r})")
        try:
            scores = ScreenScores.from_json(data["scores"])
            conditions = ScreenConditions(**data["conditions"])
            rest = {f.name: data[f.name] for f in fields(cls)[2:4]}
            rest["extraction_seconds"] = data.get("extraction_seconds")  # absent before it
            rest["extraction_runtime"] = data.get("extraction_runtime")  # absent before it
        except (KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"{type(e).__name__}: {e}") from None
        for proxy, values in scores.proxies.items():
            if GAIN not in values:
                raise ValueError(f"proxy {proxy} has no gain")
        return cls(scores, conditions, **rest)


def new_screen_record(scores: ScreenScores, conditions: ScreenConditions,
                      feature_seconds: float, extraction_seconds: float | None = None,
                      extraction_runtime: str | None = None) -> ScreenRecord:
    created = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    return ScreenRecord(scores, conditions, feature_seconds, created, extraction_seconds,
                        extraction_runtime)


@dataclass(frozen=True)
class ScreenFailure:
    """An encoder that could not be screened (build or extraction failed): its one-line reason.
    Never used to skip work: a later run screens it again."""

    backbone: str
    suite: str
    encoder: str
    error: str

    @property
    def screen_id(self) -> str:
        return screen_id(self.backbone, self.suite, self.encoder)

    def to_json(self) -> dict:
        return {_STATUS: FAILED, **asdict(self)}

    @classmethod
    def from_json(cls, data: dict) -> "ScreenFailure":
        try:
            return cls(*(str(data[f.name]) for f in fields(cls)))
        except (KeyError, TypeError) as e:
            raise ValueError(f"not a screen failure: {type(e).__name__}: {e}") from None


def read_screen(data: dict) -> ScreenRecord | ScreenFailure:
    """A stored screen file's object as what it is; ValueError when neither."""
    if _status(data) == FAILED:
        return ScreenFailure.from_json(data)
    return ScreenRecord.from_json(data)


def _status(data) -> object:
    return data.get(_STATUS) if isinstance(data, dict) else type(data).__name__


@dataclass(frozen=True)
class ScreenSelection:
    """What a --screen run grafts on backbone x suite: the top `keep` (None: all) by `by`, the
    references always, and every dropped encoder with why (its rank and score, or its failure).
    `calibration`: the results dir of the calibration study the run named
    (--screen-calibration), whose agreement the report quotes; None when it named none."""

    backbone: str
    suite: str
    by: str
    keep: int | None
    kept: tuple[str, ...]
    references: tuple[str, ...]
    dropped: dict = field(default_factory=dict)  # encoder -> one line
    note: str | None = None
    calibration: str | None = None

    def grafts(self, encoder: str) -> bool:
        return encoder in self.kept or encoder in self.references

    def to_json(self) -> dict:
        return {**asdict(self), "kept": list(self.kept), "references": list(self.references)}

    @classmethod
    def from_json(cls, data: dict) -> "ScreenSelection":
        try:
            return cls(**{**data, "kept": tuple(data["kept"]),
                          "references": tuple(data["references"]),
                          "dropped": dict(data["dropped"])})
        except (KeyError, TypeError) as e:
            raise ValueError(f"not a screen selection: {type(e).__name__}: {e}") from None
