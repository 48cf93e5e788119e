"""Real scans against the simulated sensor: reading them and adopting their camera, simulating each real frame at its
annotated poses (with its support plane), the pixels the modelled scene can explain, the gap metric and its noise
floor, realism statistics, pictures and local patches. compare, fit, diagnose and refine all use this layer; it
never imports them."""
