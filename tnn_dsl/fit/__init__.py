"""tnn_dsl.fit."""
