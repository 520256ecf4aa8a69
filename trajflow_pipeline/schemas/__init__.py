"""The unified Parquet scene dataset: table contract, validation, reading and writing."""

from .io import Dataset, DatasetMeta, DatasetWriter, data_mismatch, open_dataset
from .tables import (AGENT_TYPES, PROTOCOL_FIXED, PROTOCOL_FOLDS, PROTOCOL_TRAIN_IS_TEST, PROTOCOLS, SAMPLES,
                     SCENES, SCHEMA_VERSION, TRACKS, TableSpec)

__all__ = ["AGENT_TYPES", "Dataset", "DatasetMeta", "DatasetWriter", "PROTOCOLS", "PROTOCOL_FIXED",
           "PROTOCOL_FOLDS", "PROTOCOL_TRAIN_IS_TEST", "SAMPLES", "SCENES", "SCHEMA_VERSION", "TRACKS",
           "TableSpec", "data_mismatch", "open_dataset"]
