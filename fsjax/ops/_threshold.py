"""Thresholds (global and local).

(conventions to be stated here)
"""

__all__: list[str] = []
