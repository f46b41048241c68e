"""tnn_dsl.estimation."""
