"""`ragsplat survey`'s stages, one a module, chained by `survey.pipeline.run`."""
