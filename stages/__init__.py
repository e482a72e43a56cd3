"""Per-frame stages (features, gradients, covariances) and aggregation (GOM + PSO, MC-GICP, sinks)."""
