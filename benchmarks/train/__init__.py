"""Training: the step and its layers, the train stage against the bare step, float32
against bf16, and which data, augmentations and per-pixel maps pay."""
