"""The package's version (one place: ``solderpyro.__version__`` and the run store's records
read it here)."""

__version__ = "0.1.0"
