"""Dataset directories as model-ready tensors, selected by the dataset's evaluation protocol."""

from .loader import Problems, build_problems, list_folds, load_problems, select_samples

__all__ = ["Problems", "build_problems", "list_folds", "load_problems", "select_samples"]
