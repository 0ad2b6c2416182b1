"""Coupled Scene Construction: the object branch and the background branch share one object
identity (the instance id).

objects/     candidates → batched Sim(3) registration → checks → selection → assets
physics/     collision parts, physics priors, MuJoCo bodies, MJCF/URDF, drop tests
background/  removal of the objects' Gaussians → inpainting targets → plane-disk fill
"""
