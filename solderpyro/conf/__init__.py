"""The packaged Hydra configs (``pkg://solderpyro.conf``): one folder per config group
(specimen, materials, loading, mesh, solver, surrogate, calibration, data, cluster,
experiment) and the primary ``config.yaml``. ``solderpyro --config-dir DIR`` puts a folder of
the user's own groups in front of these."""
