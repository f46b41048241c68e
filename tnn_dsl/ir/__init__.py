"""tnn_dsl.ir."""
