"""The image models' names, apart from their torch code: the command line offers them as choices."""

IMAGE_MODELS = ("dvr", "slice", "mip")
