"""Colour conversions.

(conventions to be stated here)
"""

__all__: list[str] = []
