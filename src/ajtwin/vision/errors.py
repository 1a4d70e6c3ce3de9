"""The vision package's errors, importable without OpenCV (a caller that only catches them
need not load it)."""


class VisionInputError(ValueError):
    """Input the extractor cannot use (unreadable/empty video, wrong pixel size, ...)."""
