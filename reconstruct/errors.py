"""The reconstruction exception tree and warning."""

from __future__ import annotations


class ReconstructionError(Exception):
    """Base of every reconstruction failure."""


class InvalidInputError(ReconstructionError, ValueError):
    """The input cannot be used: unreadable or malformed file, too few points, bad parameters."""


class DegenerateCloudError(InvalidInputError):
    """The cloud has no 2D surface to recover (collinear, or a neighbourhood graph in pieces)."""


class CloudInPiecesError(DegenerateCloudError):
    """The cloud's neighbourhood graph is in pieces that one disc-like surface cannot hold
    (several objects, or parts apart); ``sizes`` (p,) the pieces' point counts, largest first."""

    def __init__(self, message: str, sizes):
        super().__init__(message)
        self.sizes = sizes

    def __reduce__(self):  # (a worker's error is pickled back to its parent)
        return type(self), (str(self), self.sizes)


class FitError(ReconstructionError, RuntimeError):
    """A numeric step failed on valid input (embedding, training, spline fit)."""


class NotFittedError(ReconstructionError, AttributeError):
    """A step was used before ``fit``."""


class ReconstructionWarning(UserWarning):
    """Input was repaired (points dropped, a piece discarded); the result may differ."""


class WarmStartRefused(ReconstructionError):
    """A warm start cannot be used: too few points shared with the earlier fit, embeddings that
    disagree, or an earlier fit without its network (loaded from disk). Fit afresh instead."""
