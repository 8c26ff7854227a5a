"""Align: colour and geometry maths that bring datasets into one canonical space."""
