"""Demonstration data: the zarr store, format readers/writers and the sequence dataset."""

from nostra.data.dataset import SequenceDataset, make_loader, split_episodes
from nostra.data.errors import CollectionError, DataError
from nostra.data.formats import FORMATS, detect, open_source
from nostra.data.store import Store

__all__ = ["Store", "SequenceDataset", "make_loader", "split_episodes", "DataError", "CollectionError",
           "FORMATS", "detect", "open_source"]
