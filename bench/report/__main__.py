"""`python -m bench.report RESULTS_DIR`: rebuild REPORT.md from stored records (bench.report.cli
checks the input first)."""

from bench.report.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
