"""A run: its folder (every file a fit writes and everything else reads) and the training-loop skeleton."""
