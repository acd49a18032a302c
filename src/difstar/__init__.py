"""difstar."""
