"""Exceptions raised by neumesh_core. Every message says what to do about it."""


class NeuMeshError(Exception):
    """Base class for all errors raised deliberately by neumesh_core."""


class Cancelled(NeuMeshError):
    """Raised when a progress callback asked to stop (rendering, edits, undistortion, pose recovery ...)."""


class DataError(NeuMeshError):
    """A dataset is missing files, has mismatched counts or unreadable images."""


class VertexMismatchError(NeuMeshError):
    """New vertex positions do not match the field's scaffold (count or order)."""


class CheckpointError(NeuMeshError):
    """A field file is missing, truncated, corrupt or of an unknown format version."""


class WeightsUnavailableError(NeuMeshError):
    """Pretrained weights (LPIPS/DINO/...) are not present in the local cache."""


class EditError(NeuMeshError, ValueError):
    """An edit cannot run with the given input (empty region, missing UVs, incompatible fields...).
    Nothing was changed."""


class PaintMissError(EditError):
    """The paint lies on no part of the field (only background, or no scaffold vertex or atlas texel
    under it). Nothing was changed; paint over the object."""


class NoSemanticsError(NeuMeshError):
    """A semantic operation (selection, semantic render) on a field without semantic codes."""


class SelectionError(NeuMeshError):
    """A click or point does not give a region (background, outside the image, nothing similar)."""


class DeformError(NeuMeshError, ValueError):
    """A deformation cannot be set up with the given input (empty or overlapping anchor/handle sets,
    vertex indices out of range, target positions of the wrong shape).  Nothing was changed."""
