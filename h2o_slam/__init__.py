"""H₂O: flexible-cost pose-graph SLAM (hybrid Hessians), LAGO, and their ROS 2 node."""
