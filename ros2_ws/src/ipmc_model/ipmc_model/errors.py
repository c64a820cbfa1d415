"""Exceptions of ipmc_model: a small hierarchy on builtins, so callers may catch ``ValueError``."""

from __future__ import annotations


class ModelError(ValueError):
    """Base class of the errors raised by ipmc_model."""


class NotFittedError(ModelError, AttributeError):
    """A model was used (predict, simulate, save, invert) before ``fit`` was called."""


class ModelFileError(ModelError):
    """A model file is missing, corrupt, of another format, or of an unsupported format version."""


def check_fitted(model, attribute: str) -> None:
    """Raise :class:`NotFittedError` if ``model`` lacks the fitted ``attribute``."""
    if getattr(model, attribute, None) is None:
        raise NotFittedError(
            f"this {type(model).__name__} is not fitted yet; call fit(...) before using it"
        )
