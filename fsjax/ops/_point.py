"""Point and arithmetic grey-value ops.

(conventions to be stated here)
"""

__all__: list[str] = []
