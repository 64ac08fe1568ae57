"""Image features (Image -> Feature).

(conventions to be stated here)
"""

__all__: list[str] = []
