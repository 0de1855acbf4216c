"""Tables, plots and the paper's numbers."""
