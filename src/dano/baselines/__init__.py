"""The mesh path the paper argues against, built for real so that it can be measured."""
