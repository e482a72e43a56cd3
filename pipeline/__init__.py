"""Core of fleetcal: frame and transform types, camera models, config, errors, the dask engine."""
