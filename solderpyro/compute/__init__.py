"""Where FE runs are made and kept: the run store, the executor, sweeps."""
