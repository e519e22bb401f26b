"""The CNN-PS network, checkpoint I/O and the shipped weights (``models/weights``)."""
