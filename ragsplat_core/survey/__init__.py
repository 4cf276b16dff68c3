"""A surveyor's photos to a georeferenced model that ragsplat trains on: structure from motion (`sfm`),
georeferencing to RTK camera positions (`georef`), and bundle adjustment through the water (`bundle`)."""
