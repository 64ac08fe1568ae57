"""Derivatives and edge detectors.

(conventions to be stated here)
"""

__all__: list[str] = []
