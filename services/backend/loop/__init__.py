"""Loop closure and the non-causal trajectory: place recognition (bag of binary words), PnP verification,
pose graph, covisibility, keyframe history and the final bundle adjustment. It runs inside the back-end process
(:mod:`.stage` is its stage in the back-end node). No transport in here."""
