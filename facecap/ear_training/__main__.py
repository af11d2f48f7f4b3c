import sys

from facecap.ear_training.train import main

sys.exit(main())
