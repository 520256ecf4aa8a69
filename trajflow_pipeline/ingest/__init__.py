"""Raw datasets -> the unified Parquet scene dataset: one adapter per dataset and the pieces they share."""
