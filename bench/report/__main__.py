"""`python -m bench.report RESULTS_DIR`: rebuild REPORT.md from stored records."""

from bench.report.build import main

raise SystemExit(main())
