"""Held-out views of a camera dataset scored against the recovered scene, their cameras first aligned to
it, and the shape error measured from them."""
