"""Lightning training of the PINN: data module, module, and the train() function the CLI calls."""
