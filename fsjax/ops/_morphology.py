"""Grey-value morphology.

(conventions to be stated here)
"""

__all__: list[str] = []
