"""Named exceptions: every failure the user can cause has one, with a one-line message."""


class DanoError(Exception):
    """Base class of every error raised by dano on bad input."""


class FieldError(DanoError):
    """A density field is unusable: all zero, non-finite, negative, or badly shaped."""


class EmptyFieldError(FieldError):
    """The field is zero everywhere inside its box, so it has no mass and no surface."""


class NonFiniteFieldError(FieldError):
    """The field returned NaN or Inf."""


class EmptyWindowError(DanoError):
    """The density window [low, high] selects no candidate surface points."""


class MeshError(DanoError):
    """A mesh file cannot be turned into a density field."""


class MeshNotWatertightError(MeshError):
    """The mesh has holes, so its inside is undefined."""


class DanoFileError(DanoError):
    """A `.dano.npz`, grid or checkpoint file is missing, corrupt, or of another format version."""


class InvalidMassError(DanoError):
    """A mass or mass scale that is not a positive finite number."""


class SpecError(DanoError):
    """An analytic field spec such as `sphere:r=0.05` could not be parsed."""


class InvalidValueError(DanoError, ValueError):
    """A value of the wrong type or outside its physical range: a scene's, a contact parameter's, a
    command-line option's (`dano.validate`)."""
