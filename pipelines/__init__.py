"""Pipelines: the staged DAG runner (`relightanyone run`) and dataset export (`export-dataset`)."""
