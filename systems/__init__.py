"""Drake LeafSystems (plants, L1 adaptive controller, road) and the closed-loop diagram builder."""
