"""Evaluation against the synthetic world's answers: cases, metrics, tables, report, and the ``evaluate`` command."""
