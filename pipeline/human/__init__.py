"""Human motion in: SMPL skeleton, importers (GVHMR, AMASS npz, video), the bundled sample."""
