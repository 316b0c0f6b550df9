"""FE reference (dolfinx 0.5.2): Mooney-Rivlin + Prony viscoelasticity, indentation,
relaxation and gravity experiments. The only package that imports dolfinx."""
import forcecal  # noqa: F401  (settles the FFCx cache folder before dolfinx is imported: forcecal.caches)
