"""The node runtime every estimator node shares: parameters, input ordering, diagnostics, replay sync."""
