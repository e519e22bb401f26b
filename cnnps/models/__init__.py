"""The CNN-PS network, checkpoint I/O and the shipped weights (``cnnps/models/weights``)."""
