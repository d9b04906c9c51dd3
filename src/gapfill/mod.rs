//! Gap filling of motion-capture marker trajectories (Burke & Lasenby 2016). Work in progress.
