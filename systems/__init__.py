"""Drake systems: lateral plants, the L1 adaptive controller, the road, the closed-loop diagram."""
