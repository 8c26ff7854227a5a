"""The ground-truth synthetic head world.

It is the judge of every other layer, so it imports nothing from the rest of relightanyone.
"""
