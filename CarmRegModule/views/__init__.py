"""Views: CT slices, X-ray, overlay (plain Qt) and the 3D scene (VTK)."""
