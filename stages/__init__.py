"""Per-frame stages (features, gradients, covariances), aggregation (GOM + PSO, MC-GICP), result sinks."""
