"""Pipelines: staged DAG runner, OLAT expansion, relight/export and the report."""
