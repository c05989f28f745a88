# cmake -DIN=file -DOUT=file.cc -DVAR=name -P EmbedFile.cmake: writes `extern const char name[] = "...";`.
file(READ ${IN} content HEX)
string(REGEX REPLACE "([0-9a-f][0-9a-f])" "'\\\\x\\1'," content "${content}")
file(WRITE ${OUT} "// Generated from ${IN} by cmake/EmbedFile.cmake. Do not edit.\n"
                  "extern const char ${VAR}[];\nconst char ${VAR}[] = {${content} '\\0'};\n")
