/* The x86-64-v3 (AVX2 + FMA) build of the compositor: setup.py compiles this file with
 * -march=x86-64-v3. A separate file so that its object does not overwrite the baseline's. */
#include "_composite.c"
