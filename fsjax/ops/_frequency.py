"""Frequency-domain filters.

(conventions to be stated here)
"""

__all__: list[str] = []
