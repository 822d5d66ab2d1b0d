"""Warp kernels of perch_warp (installed as `perch_warp.kernels`).

render   -- kernel #1: ray-cast the textured mesh for a batch of candidate poses.
features -- kernel #2: AlexNet-conv1 features of the composited candidate and its
            rarity-weighted cosine similarity with the photo's features.
boxes    -- candidates' pixel boxes: the mesh's hull points projected for each pose.
reduce   -- the top-α mean of each candidate's feature-point scores (one float back per candidate).
raycast_bench -- `perch_warp bench`'s microbenchmark: one ray per pixel, hit depth only.
"""
