"""trajflow: raw trajectory datasets -> unified Parquet scenes -> TrajFlow models -> paper-grade metrics."""

__version__ = "0.1.0"
