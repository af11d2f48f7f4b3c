"""facecap_core: the science of facecap — pure functions over numpy/trimesh, no Prefect."""

from facecap_core.errors import FacecapError, InputError

__all__ = ["FacecapError", "InputError"]
__version__ = "0.1.0"
