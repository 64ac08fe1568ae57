"""Binary morphology on Region.

(conventions to be stated here)
"""

__all__: list[str] = []
