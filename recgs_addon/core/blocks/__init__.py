"""A survey trained in blocks: the split over the seabed (``split``) and the merge of the
blocks' Gaussians into one scene, with its scores (``merge``). Running the blocks is the
``train --blocks`` command's (commands/blocks.py, on Ray)."""
