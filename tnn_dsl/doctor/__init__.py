"""tnn_dsl.doctor."""
