"""The thread-free SLAM core: frames in, poses, objects and loops out."""
