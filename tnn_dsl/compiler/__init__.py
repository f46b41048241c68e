"""tnn_dsl.compiler."""
