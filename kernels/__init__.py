"""Warp kernels of perch_warp (installed as `perch_warp.kernels`).

render   -- kernel #1: ray-cast the textured mesh for a batch of candidate poses.
features -- kernel #2: AlexNet-conv1 features of the composited candidate and its
            rarity-weighted cosine similarity with the photo's features.
raycast_bench -- `perch_warp bench`'s microbenchmark: one ray per pixel, hit depth only.
"""
