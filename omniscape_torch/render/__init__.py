"""Rendering a cubemap into any camera: the layer, its samplers and the uses built on it."""
