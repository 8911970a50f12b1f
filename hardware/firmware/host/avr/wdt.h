#pragma once
#define WDTO_250MS 4
inline void wdt_enable(int) {}
inline void wdt_disable() {}
inline void wdt_reset() {}
