"""3D maps from RGB + ToF depth: TSDF fusion (Open3D), camera poses, odometry, map metrics."""
