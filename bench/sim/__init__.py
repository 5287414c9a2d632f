"""One landing: build the world, fly the closed loop, and render its views."""
