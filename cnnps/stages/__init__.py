"""One module per pipeline stage; each exposes ``run(config)`` taking its typed params section."""
