"""tnn_dsl.core."""
