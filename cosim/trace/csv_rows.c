/* orjson's text of a 2-D array without its outer brackets ("1e-7,0.00006],[2.5,...") -> CSV
   lines in repr's notation (cosim/trace/text.py); returns the bytes written to out (at most
   n + n / 2 + 1). */
#include <stddef.h>
#include <string.h>
static int digit(char c) { return c >= '0' && c <= '9'; }
size_t rpr_csv_rows(const char *in, size_t n, char *out) {
    size_t i = 0, o = 0;
    int start = 1;                       /* at the first character of a number */
    while (i < n) {
        char c = in[i];
        if (start) {
            start = 0;
            size_t j = i;
            if (c == '-') { out[o++] = '-'; j++; }
            if (n - j >= 7 && memcmp(in + j, "0.0000", 6) == 0 && in[j + 6] >= '1' && in[j + 6] <= '9') {
                size_t k = j + 7;        /* 0.0000DDD -> D.DDe-05 */
                while (k < n && digit(in[k])) k++;
                out[o++] = in[j + 6];
                if (k > j + 7) { out[o++] = '.'; memcpy(out + o, in + j + 7, k - j - 7); o += k - j - 7; }
                memcpy(out + o, "e-05", 4); o += 4;
                i = k;
                continue;
            }
            i = j;
            continue;
        }
        if (c == ',') { out[o++] = ','; start = 1; i++; }
        else if (c == ']') { out[o++] = '\n'; start = 1; i += 3; }  /* "],[": the next row */
        else if (c == 'e' && i + 2 < n && in[i + 1] == '-' && digit(in[i + 2])
                 && (i + 3 >= n || !digit(in[i + 3]))) {                /* e-7 -> e-07 */
            memcpy(out + o, "e-0", 3); o += 3; out[o++] = in[i + 2]; i += 3;
        }
        else { out[o++] = c; i++; }
    }
    out[o++] = '\n';
    return o;
}
