"""Ingest: one adapter per native dataset layout, all producing normalized records."""
