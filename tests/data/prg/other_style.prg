#0
! Second post style of Optomec AJ programs, written by hand for the tests from the
! ACSPL+ command reference: upper-case commands, speeds in variables (LINE/V ..., speed),
! ARC1 (centre, end point, direction), the shutter on digital output 0 bit 0, dwells in
! variables (ms), feature comments. Hand figures: docs in tests/test_job_geometry.py.
GLOBAL REAL gDblRapidSpeed
GLOBAL REAL gDblProcessSpeed
REAL OpenDelay, CloseDelay
gDblRapidSpeed = 20
gDblProcessSpeed = 3
OpenDelay = 50
CloseDelay = 20
VEL(X) = 5

!Feature 1 outline
PTP/EV (X,Y), 1, 1, gDblRapidSpeed
OUT0.0=1
WAIT OpenDelay
MSEG (X,Y), 1, 1
LINE/V (X,Y), 4, 1, gDblProcessSpeed
ARC1 (X,Y), 4, 2, 4, 3, +
LINE/V (X,Y), 1, 3, gDblProcessSpeed
ENDS (X,Y)
TILL ^X_AST.#MOVE & ^Y_AST.#MOVE
OUT0.0=0
WAIT CloseDelay

!Feature 2 bar
PTP/EV (X,Y), 10, 1, gDblRapidSpeed
OUT0.0=1
WAIT OpenDelay
PTP/E (X,Y), 12, 1           ! at VEL(X)
OUT0.0=0
WAIT CloseDelay
HALT ALL
STOP
