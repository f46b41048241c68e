"""tnn_dsl.lang."""
