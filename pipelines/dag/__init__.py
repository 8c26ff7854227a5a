"""The staged DAG runner behind ``relightanyone run``: pipeline files, fingerprints, stage records, execution."""
