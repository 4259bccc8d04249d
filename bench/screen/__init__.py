"""The screen tier (`pytest bench --screen`): zero-training proxies of many encoders from their
stored features, and which of them the graft runs.

    proxies.py     the proxy table: one `register_proxy(Proxy(...))` per proxy (no torch)
    estimators.py  the proxies' numerics: LogME, ridge and k-NN probes, norm entropy (numpy)
    spectral.py    their one decomposition (D x D or N x N, the cheaper) and LogME's maximum
    synthetic.py   screen inputs at the real study's size, for the benchmark and tests
    measure.py     one screen from the feature store: `measure_screen` (torch)
    selection.py   --screen-by / --screen-keep, and what is grafted (no torch)
    records.py     the stored screen, failure and selection, typed (no torch)

Outside it, by layer: bench.cell.screening runs the screens of one pytest run (locks, the
store, the short grafts); bench.report.screen writes REPORT.md's section. This package sits
below bench.results (which stores its records) and imports nothing of the analysis or report.
"""
