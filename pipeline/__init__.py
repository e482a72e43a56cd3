"""Core of fleetcal: frame and transform types, camera models, config, errors, message-type names, the dask engine."""
