"""The other commands and the stages' machinery: ``cnnps calibrate`` and ``cnnps
integrate``, the executors, and runs killed on purpose."""
