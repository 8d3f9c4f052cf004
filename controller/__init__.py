"""Control laws and their discretisation."""
