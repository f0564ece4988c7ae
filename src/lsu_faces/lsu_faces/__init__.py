"""Meshing, smoothing, texture, renders, nose tip, spherical embedding, face gallery and the face_processor node."""
