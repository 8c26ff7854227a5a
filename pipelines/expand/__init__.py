"""The OLAT expansion job behind ``relightanyone expand``: plan, per-subject tasks, avatars, rendering."""
