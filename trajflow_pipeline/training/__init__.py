"""`trajflow train DATA -o RUN`: fit a model's training stages on a dataset split, resumably (what it promises:
`trajflow train` in docs/usage.md). :func:`train` is the entry point; the loop is :mod:`.loop`."""

from .policy import (BUDGET_KEYS, REFIT_MODEL_KEYS, autoencoder_start, budget_raise, budget_size, describe_refit,
                     first_difference, raise_blocker, refit_change, refit_matters)
from .run import train
from .state import check_state, read_state, state_config

__all__ = ["BUDGET_KEYS", "REFIT_MODEL_KEYS", "autoencoder_start", "budget_raise", "budget_size", "check_state",
           "describe_refit", "first_difference", "raise_blocker", "read_state", "refit_change", "refit_matters",
           "state_config", "train"]
