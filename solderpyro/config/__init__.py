"""Configuration: the typed settings, composing the YAML configs, the run directory."""
