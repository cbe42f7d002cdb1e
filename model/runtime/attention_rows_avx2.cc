// The fused attention loop for AVX2 + FMA (see attention_rows_impl.h).
// Compiled with -mavx2 -mfma; called only where the CPU has both.
#define CPU_CAPABILITY AVX2
#define CPU_CAPABILITY_AVX2
#define FD_ATTENTION_ROWS_FN AttendHeadsAvx2
#include "model/runtime/attention_rows_impl.h"
