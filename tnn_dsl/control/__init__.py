"""tnn_dsl.control."""
