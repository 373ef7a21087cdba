"""The main job on built-in defaults (``make demo`` = ``python -m demo``): datagen, training and
inference end to end. It orchestrates the three packages, so it lives beside them.
"""
