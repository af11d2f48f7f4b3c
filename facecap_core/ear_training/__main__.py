import sys

from facecap_core.ear_training.train import main

sys.exit(main())
