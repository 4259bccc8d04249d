"""REPORT.md from stored records: context, sections, provenance, plots, the study table."""
