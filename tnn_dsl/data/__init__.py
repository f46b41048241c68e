"""tnn_dsl.data."""
