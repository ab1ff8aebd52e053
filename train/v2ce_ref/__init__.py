"""Reference (PyTorch) implementation of the V2CE Stage 1 network and helpers.

Used only offline: to make the parity fixtures under tests/fixtures/learned/ and to
benchmark the reference network. Nothing in the Rust crate needs it at run time.

Modules:
    model     -- V2ce3d / UNet3D with the official parameter names (spec 3, Appendix A)
    seeded    -- the deterministic seeded checkpoint the Rust tests reproduce bit-for-bit
    pipeline  -- toolbox preprocessing, sequence planning and merge (spec 1.2, 1.3)
    png       -- a minimal 8-bit grayscale PNG reader/writer (no Pillow needed)
"""
