"""Motion I/O: read the field's SMPL-X formats as y-up, absolute-hand `Motion`s, write npz.

Formats: AMASS SMPL-X/SMPL+H npz, SOKE per-frame pkl folders (+ split index), SignAvatars pkl,
plain npy/npz arrays, and embody's own npz (written by `save`).
"""

from embody.io.amass import save
from embody.io.dataset import Dataset, SequenceRef, load_dataset
from embody.io.hands import absolute_to_relative, hand_mean, relative_to_absolute
from embody.io.loader import load

__all__ = ["Dataset", "SequenceRef", "absolute_to_relative", "hand_mean", "load", "load_dataset",
           "relative_to_absolute", "save"]
