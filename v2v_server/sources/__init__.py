"""Where the videos come from and how they are decoded: corpus scanning and sharding, each file's
verdict, sequential luma decoding."""
