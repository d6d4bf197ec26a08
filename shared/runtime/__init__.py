"""The runtime every service shares, whatever carries its messages: the :class:`Bus` a
session talks through (Zenoh or in-process) and the :class:`StatusBook` it reports from.

Nothing here imports zenoh; ``shared.transport`` holds the Zenoh implementation.
"""
