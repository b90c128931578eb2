"""arraycontact: exact closest-point contact detection for finite-element surfaces.

`detect(slave, master)` finds, for every slave node, the closest point on the master surface:
contact face, natural coordinates, point, signed gap, normal and feature. Back ends: NumPy
(default), JAX (`backend="jax"`) and Warp (`backend="warp"`), loaded only when asked for.
"""

from . import reference as reference
from . import scenes as scenes
from ._contacts import Contacts as Contacts
from ._contacts import Counts as Counts
from ._contacts import Feature as Feature
from ._contacts import Status as Status
from ._contacts import SweptContacts as SweptContacts
from ._detect import detect as detect
from ._detect import detect_self as detect_self
from ._detect import detect_swept as detect_swept
from ._elements import ELEMENTS as ELEMENTS
from ._io import read_surface as read_surface
from ._io import surface_from_meshio as surface_from_meshio
from ._partition import Partition as Partition
from ._partition import partition as partition
from ._prepare import default_d_max as default_d_max
from ._surface import Surface as Surface

__version__ = "0.1.0"
__all__ = [
    "Contacts",
    "Counts",
    "Feature",
    "Status",
    "Surface",
    "detect",
    "detect_self",
    "detect_swept",
    "SweptContacts",
    "default_d_max",
    "Partition",
    "partition",
    "read_surface",
    "surface_from_meshio",
    "reference",
    "scenes",
    "ELEMENTS",
]
