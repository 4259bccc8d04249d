"""The naive baselines of screens stored before them, computed when the report is built.

A screen measured before the naive baselines joined the proxy table holds no parameter count,
FLOPs or input resolution. They read nothing but the encoder, so the report builds it the way its
grafts' records say it was built (the registry, the record's world: bench.analysis.candidates)
and counts them (encoders.cost), once per encoder and world. A screen that holds them keeps its
own. An encoder that cannot be built here leaves them undefined, saying why.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from typing import Sequence

from bench.analysis.candidates import profile_source
from bench.grid.kinds import GRAFT
from bench.screen.proxies import naive_proxies
from bench.screen.records import GAIN, VALUE, ScreenScores
from bench.stats import Measure, Undefined

AT_REPORT_TIME = ("measured before the naive baselines joined the screen: counted when this "
                  "report was built, from the encoder the registry builds in its grafts' world")


@lru_cache(maxsize=None)
def _cost(encoder: str, source: str):
    """encoders.cost.EncoderCost of `encoder` built for `source`, or Undefined saying why not."""
    from encoders import build_encoder
    from encoders.cost import encoder_cost

    try:
        return encoder_cost(build_encoder(encoder, source))
    except Exception as e:  # noqa: BLE001 - any encoder may fail to build here; said, not raised
        return Undefined(f"{encoder} could not be built for its cost here: {type(e).__name__}: "
                         + " ".join(str(e).split())[:200])


def _values(screen: ScreenScores, records: Sequence) -> dict[str, Measure]:
    """{naive baseline: value} of one screen's encoder, from its grafts' world."""
    sources = {profile_source(r.measured.profile) for r in records
               if r.kind == GRAFT and (r.backbone, r.suite, r.encoder)
               == (screen.backbone, screen.suite, screen.encoder)}
    sources.discard(None)
    if len(sources) != 1:
        why = Undefined(f"{screen.encoder}: its grafts name {len(sources)} known worlds "
                        f"({sorted(sources)}), not one: which encoder was screened is not known")
        return {p.name: why for p in naive_proxies()}
    cost = _cost(screen.encoder, sources.pop())
    return {p.name: cost if isinstance(cost, Undefined) else p.compute(cost)
            for p in naive_proxies()}


def with_naive_baselines(screens: Sequence[ScreenScores], records: Sequence
                         ) -> tuple[list[ScreenScores], list[str]]:
    """(every screen holding every naive baseline, the screens' ids whose were computed here):
    a screen's own values where it holds them, else counted now (module doc)."""
    out, filled = [], []
    for screen in screens:
        missing = [p for p in naive_proxies() if not screen.holds(p.name)]
        if not missing:
            out.append(screen)
            continue
        values = _values(screen, records)
        proxies = dict(screen.proxies)
        for p in missing:
            proxies[p.name] = {VALUE: values[p.name], GAIN: p.oriented(values[p.name])}
        out.append(dataclasses.replace(screen, proxies=proxies))
        filled.append(f"{screen.backbone}-{screen.suite}-{screen.encoder}")
    return out, filled
