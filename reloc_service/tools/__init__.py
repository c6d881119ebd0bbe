"""The tools around the relocalizer: evaluation (``eval``), datasets (``data``), synthetic scenes
(``synth``), benchmarks (``bench``) and the demo. Not needed to serve: their extra dependencies
(scikit-image, matplotlib) come with ``pip install reloc[tools]``. The core and the service never
import this package."""
